"""Map files (issue 17 item 3): the Atlas saved and read back exactly; bad files (truncated, a flipped byte, another
schema version, another vocabulary), an unwritable path and a crash mid-save each give a MapFileError naming the file,
and nothing is loaded. A small hand-built Atlas of two maps here; the real room map is in
tests/integration/test_map_files.py."""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from slamkit_dbow.recognizer import DbowPlaceRecognizer

from slamkit.errors import MapFileError
from slamkit.features import Features, Observations
from slamkit.geometry.camera import KannalaBrandtCamera, PinholeCamera
from slamkit.interfaces import MapStore
from slamkit.map import mapfile
from slamkit.map.atlas import Atlas
from slamkit.map.entities import KeyFrame, MapPoint
from slamkit.map.ids import IdAllocator
from slamkit.map.mapfile import load_atlas, map_file_info, save_atlas
from slamkit.map.mapfile_contents import differences, read_map_contents
from slamkit.map.store import InMemoryMapStore

CAMERA = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0, dist=(0.01, -0.002, 0.0, 0.0, 0.0))
FISHEYE = KannalaBrandtCamera(640, 480, 300.0, 300.0, 320.0, 240.0, k=(0.01, 0.0, 0.0, 0.0))
N_FEATS = 80


def new_store(ids: IdAllocator) -> MapStore:
    return InMemoryMapStore(ids=ids)


def observations(rng: np.random.Generator, camera: Any, stereo: bool) -> Observations:
    uv = rng.uniform(0, 480, (N_FEATS, 2)).astype(np.float32)
    feats = Features(
        uv,
        (uv + 0.25).astype(np.float32),
        rng.integers(0, 8, N_FEATS).astype(np.int32),
        rng.uniform(0, 360, N_FEATS).astype(np.float32),
        rng.uniform(0, 1, N_FEATS).astype(np.float32),
        rng.integers(0, 256, (N_FEATS, 32), dtype=np.uint8),
        1.2,
        8,
    )
    obs = Observations.monocular(feats, camera.unproject_image(feats.uv_undist_px.astype(np.float64)))
    if not stereo:
        return obs
    depth = rng.uniform(1, 5, N_FEATS).astype(np.float32)
    depth[::7] = np.nan
    return Observations(
        **{name: getattr(obs, name) for name in Features.__dataclass_fields__},
        bearing=obs.bearing,
        u_right_px=(uv[:, 0] - 40.0 / depth).astype(np.float32),
        depth_m=depth,
        bf=40.0,
        th_depth_m=3.2,
        sensor="rgbd",
    )


def fill_map(atlas: Atlas, rng: np.random.Generator, n_kfs: int, camera: Any, stereo: bool = False) -> None:
    """Keyframes along x with bags of words, points seen by 2-4 of them, graphs, counters, a loop edge, a culled
    keyframe and culled points: every part of a map's state."""
    store, place = atlas.active, atlas.place
    assert place is not None
    kf_ids: list[int] = []
    free: dict[int, int] = {}
    for i in range(n_kfs):
        kf_id = store.new_keyframe_id()
        T = np.eye(4)
        T[0, 3] = -0.1 * i
        feats = observations(rng, camera, stereo)
        store.add_keyframe(KeyFrame(kf_id, 3 * i, 0.1 * i, T, camera, feats, np.full(N_FEATS, -1, np.int64)))
        bow = place.transform(feats.descriptors)
        store.set_keyframe_bow(kf_id, bow)
        place.add(kf_id, bow)
        kf_ids.append(kf_id)
        free[kf_id] = 0
        if i == 0:
            continue
        for j in range(25):  # points seen by this keyframe and up to 3 before it (as local mapping makes them)
            observers = kf_ids[max(0, i - int(rng.integers(1, 4))) :]
            pid = store.new_point_id()
            point = MapPoint(
                pid,
                rng.uniform([-1, -1, 3], [1, 1, 6]),
                rng.integers(0, 256, 32).astype(np.uint8),
                observers[0],
                observers[0],
                rng.normal(size=3),
                0.5 + j * 1e-3,
                7.0,
            )
            store.add_point(point)
            for k in observers:
                if free[k] < N_FEATS:
                    store.add_observation(pid, k, free[k])
                    free[k] += 1
        if i == 1:
            store.update_connections(kf_ids[0])
        store.update_connections(kf_id)
    pids = np.array(store.point_ids(), np.int64)
    store.increase_visible(pids[::2], 3)
    store.increase_found(pids[::3], 2)
    store.add_loop_edge(kf_ids[0], kf_ids[-1])
    store.remove_keyframe(kf_ids[2])
    place.remove(kf_ids[2])
    for pid in store.point_ids()[:5]:
        store.remove_point(pid)
    store.bump_epoch()


@pytest.fixture(scope="module")
def place() -> DbowPlaceRecognizer:
    return DbowPlaceRecognizer()


def build_atlas(place: DbowPlaceRecognizer, seed: int = 0) -> Atlas:
    """Two maps: map 0 monocular pinhole, map 1 (active) RGB-D-like keyframes on a fisheye camera."""
    place.database.clear()
    atlas = Atlas(new_store, place)
    rng = np.random.default_rng(seed)
    fill_map(atlas, rng, 8, CAMERA)
    atlas.create_map()
    fill_map(atlas, rng, 6, FISHEYE, stereo=True)
    return atlas


def assert_same_atlas(a: Atlas, b: Atlas) -> None:
    assert a.map_ids() == b.map_ids()
    assert a.active_id == b.active_id
    assert a.next_map_id == b.next_map_id
    assert a.ids.next_ids() == b.ids.next_ids()
    for map_id, store in a.items():
        diff = differences(read_map_contents(store), read_map_contents(b.get(map_id)))
        assert not diff, f"map {map_id}: {diff}"


def test_round_trip_is_exact(tmp_path: Path, place: DbowPlaceRecognizer) -> None:
    atlas = build_atlas(place)
    path = tmp_path / "room.slamkit"
    info = save_atlas(atlas, path, config={"seed": 0, "pipeline": {"x": 1.5}})
    assert info.size_bytes == path.stat().st_size
    assert info.maps == tuple((m, s.n_keyframes(), s.n_points()) for m, s in atlas.items())
    fresh = DbowPlaceRecognizer()
    loaded = load_atlas(path, new_store, fresh)
    assert_same_atlas(atlas, loaded)
    # the keyframe database holds every saved keyframe with its bag of words
    assert sorted(fresh.database.keyframe_ids()) == sorted(place.database.keyframe_ids())
    for kf_id in place.database.keyframe_ids():
        assert fresh.database.bow(kf_id).words == place.database.bow(kf_id).words
    # the loaded Atlas goes on: new ids follow the saved ones, and a new map gets the next map id
    assert loaded.active.new_keyframe_id() == atlas.active.new_keyframe_id()
    assert loaded.create_map() == atlas.create_map()
    # the file is a plain .npz: numpy opens it without pickling
    with np.load(path, allow_pickle=False) as npz:
        assert npz["m1/kf_id"].tolist() == atlas.get(1).keyframe_ids()
    assert mapfile.read_manifest(path)["config"] == {"seed": 0, "pipeline": {"x": 1.5}}


def test_run_cameras_are_reused_on_load(tmp_path: Path, place: DbowPlaceRecognizer) -> None:
    atlas = build_atlas(place)
    save_atlas(atlas, tmp_path / "m.slamkit")
    same = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0, dist=(0.01, -0.002, 0.0, 0.0, 0.0))
    loaded = load_atlas(tmp_path / "m.slamkit", new_store, DbowPlaceRecognizer(), cameras=[same])
    store = loaded.get(0)
    assert all(store.get_keyframe(k).camera is same for k in store.keyframe_ids())
    fish = loaded.get(1)
    assert all(fish.get_keyframe(k).camera.to_dict() == FISHEYE.to_dict() for k in fish.keyframe_ids())  # type: ignore[attr-defined]


def test_info(tmp_path: Path, place: DbowPlaceRecognizer) -> None:
    atlas = build_atlas(place)
    path = tmp_path / "m.slamkit"
    save_atlas(atlas, path)
    info = map_file_info(path)
    assert info.schema_version == mapfile.SCHEMA_VERSION
    assert info.active_map_id == 1
    assert info.n_keyframes == sum(s.n_keyframes() for _, s in atlas.items())
    assert info.n_points == sum(s.n_points() for _, s in atlas.items())
    assert info.vocabulary is not None and info.vocabulary["sha256"] == place.vocabulary.identity()["sha256"]


# ---- bad input: a clear error naming the file, nothing loaded --------------------------------------------------


class RecordingPlace(DbowPlaceRecognizer):
    """A keyframe database that counts what is added to it (nothing may be, when a load fails)."""

    def __init__(self) -> None:
        super().__init__()
        self.added = 0

    def add(self, keyframe_id: int, bow: Any) -> None:
        self.added += 1
        super().add(keyframe_id, bow)


def refused(path: Path, match: str, place: DbowPlaceRecognizer | None = None) -> MapFileError:
    place = place if place is not None else RecordingPlace()
    with pytest.raises(MapFileError, match=match) as err:
        load_atlas(path, new_store, place)
    assert str(path) in str(err.value)
    assert isinstance(place, RecordingPlace) and place.added == 0
    return err.value


@pytest.fixture
def saved(tmp_path: Path, place: DbowPlaceRecognizer) -> Path:
    path = tmp_path / "m.slamkit"
    save_atlas(build_atlas(place), path)
    return path


def test_truncated_file(saved: Path) -> None:
    data = saved.read_bytes()
    for keep in (0, 10, len(data) // 2, len(data) - 1):
        saved.write_bytes(data[:keep])
        refused(saved, "truncated or not a slamkit map file")


def test_flipped_byte(saved: Path) -> None:
    data = bytearray(saved.read_bytes())
    for offset in (40, len(data) // 3, len(data) - 100, len(data) - 5):
        flipped = bytearray(data)
        flipped[offset] ^= 0x10
        saved.write_bytes(bytes(flipped))
        refused(saved, "checksum mismatch|corrupted")


def test_future_schema_version(saved: Path, tmp_path: Path) -> None:
    manifest = mapfile.read_manifest(saved)
    manifest["schema_version"] = mapfile.SCHEMA_VERSION + 1
    with zipfile.ZipFile(saved) as zf:
        members = [(n, np.load(zf.open(n), allow_pickle=False)) for n in zf.namelist() if n.endswith(".npy")]
    future = tmp_path / "future.slamkit"
    mapfile._write(future, manifest, members, mapfile.SCHEMA_VERSION + 1)
    err = refused(future, "schema version 2")
    assert "reads schema version 1" in str(err)


def test_other_vocabulary(saved: Path, place: DbowPlaceRecognizer) -> None:
    class OtherVocabulary(RecordingPlace):
        def vocabulary_identity(self) -> dict[str, object]:
            return {"name": "other", "sha256": "0" * 64, "words": 10}

    refused(saved, "another vocabulary", OtherVocabulary())


def test_vocabulary_identity_follows_the_vocabulary(place: DbowPlaceRecognizer) -> None:
    from slamkit_dbow.vocabulary import Vocabulary

    v = place.vocabulary
    weights = v.weights.copy()
    weights[v.word_nodes[0]] *= 1.5
    other = Vocabulary(v.k, v.L, v.parent, v.descriptors, weights, v.is_leaf, v.scoring, v.weighting)
    assert other.identity()["sha256"] != v.identity()["sha256"]
    same = Vocabulary(v.k, v.L, v.parent, v.descriptors, v.weights, v.is_leaf, v.scoring, v.weighting)
    assert same.identity() == v.identity()


def test_inconsistent_contents_load_nothing(saved: Path, tmp_path: Path) -> None:
    """A well-formed file (valid checksum) whose contents disagree: observations pointing at the wrong feature."""
    manifest = mapfile.read_manifest(saved)
    with zipfile.ZipFile(saved) as zf:
        members = [(n, np.load(zf.open(n), allow_pickle=False)) for n in zf.namelist() if n.endswith(".npy")]
    members = [(n, a + 1 if n == "m1/obs_feature.npy" else a) for n, a in members]
    bad = tmp_path / "bad.slamkit"
    mapfile._write(bad, manifest, members, mapfile.SCHEMA_VERSION)
    refused(bad, "inconsistent contents")


def test_not_a_map_file(tmp_path: Path) -> None:
    path = tmp_path / "notes.slamkit"
    path.write_text("hello\n")
    refused(path, "truncated or not a slamkit map file")
    refused(tmp_path / "missing.slamkit", "no such file")


def test_unwritable_path(tmp_path: Path, place: DbowPlaceRecognizer) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    target = blocker / "map.slamkit"  # its "directory" is a file
    with pytest.raises(MapFileError, match="cannot be written") as err:
        save_atlas(build_atlas(place), target)
    assert str(target) in str(err.value)


def test_crash_mid_save_keeps_the_previous_file(
    saved: Path, place: DbowPlaceRecognizer, monkeypatch: pytest.MonkeyPatch
) -> None:
    before = saved.read_bytes()
    calls = {"n": 0}
    write_array = np.lib.format.write_array

    def crash_on_the_tenth(*args: Any, **kwargs: Any) -> None:
        calls["n"] += 1
        if calls["n"] == 10:
            raise KeyboardInterrupt  # stands for a kill mid-save
        write_array(*args, **kwargs)

    monkeypatch.setattr(np.lib.format, "write_array", crash_on_the_tenth)
    with pytest.raises(KeyboardInterrupt):
        save_atlas(build_atlas(place, seed=1), saved)
    monkeypatch.undo()
    assert saved.read_bytes() == before
    assert os.listdir(saved.parent) == [saved.name], "the temporary file is removed"
    load_atlas(saved, new_store, DbowPlaceRecognizer())


def test_manifest_is_json(saved: Path) -> None:
    with zipfile.ZipFile(saved) as zf:
        manifest = json.loads(zf.read("manifest.json"))
    assert manifest["format"] == "slamkit-map"
    assert {m["id"] for m in manifest["maps"]} == {0, 1}
