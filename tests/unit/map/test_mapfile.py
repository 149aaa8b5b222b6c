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
from mapfile_atlas import FISHEYE, FISHEYE_2, RecordingPlace, build_atlas, build_frames, build_rig_atlas, new_store
from slamkit_dbow.recognizer import DbowPlaceRecognizer

from slamkit.errors import ConfigError, MapFileError
from slamkit.geometry.camera import PinholeCamera
from slamkit.map import mapfile
from slamkit.map.atlas import Atlas
from slamkit.map.mapfile import load_atlas, map_file_info, save_atlas
from slamkit.map.mapfile_contents import differences, read_map_contents
from slamkit.sensors import FrameRecords


@pytest.fixture(scope="module")
def place() -> DbowPlaceRecognizer:
    return DbowPlaceRecognizer()


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
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask, "the usual mode of a new file, not mkstemp's 0600"
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


def test_a_rig_map_round_trips_with_its_second_camera(tmp_path: Path, place: DbowPlaceRecognizer) -> None:
    """frontend=stereo_rig's keyframes (ORB-SLAM3 sec. I-B): camera 2's keypoints, the stereo matches, the triangulated
    points, the second camera's model and T_c2_c1 come back exactly, in a file of schema version 2 (a reader of
    version 1 refuses it rather than dropping the second camera); a file without them stays version 1."""
    atlas = build_rig_atlas(place)
    path = tmp_path / "rig.slamkit"
    info = save_atlas(atlas, path)
    assert info.schema_version == mapfile.RIG_SCHEMA_VERSION
    loaded = load_atlas(path, new_store, DbowPlaceRecognizer())
    assert_same_atlas(atlas, loaded)
    rig = loaded.get(1)
    for k in rig.keyframe_ids():
        f = rig.get_keyframe(k).features
        assert f.two_cameras and f.n_left == 40 and f.camera_2.to_dict() == FISHEYE_2.to_dict()
    mono = loaded.get(0)
    assert not any(mono.get_keyframe(k).features.two_cameras for k in mono.keyframe_ids())
    # the run's cameras are reused for the second camera too
    again = load_atlas(path, new_store, DbowPlaceRecognizer(), cameras=[FISHEYE, FISHEYE_2])
    assert all(again.get(1).get_keyframe(k).features.camera_2 is FISHEYE_2 for k in again.get(1).keyframe_ids())
    # a one-way stereo link is inconsistent: refused, nothing loaded
    with zipfile.ZipFile(path) as zf:
        members = [(n, np.load(zf.open(n), allow_pickle=False)) for n in zf.namelist() if n.endswith(".npy")]
    broken = []
    for name, array in members:
        if name == "m1/feat_stereo_match.npy":
            array = array.copy()
            array[int(np.flatnonzero(array >= 0)[0])] = 41  # camera 1 -> another camera-2 keypoint
        broken.append((name, array))
    bad = tmp_path / "bad.slamkit"
    mapfile._write(bad, mapfile.read_manifest(path), broken, mapfile.RIG_SCHEMA_VERSION)
    refused(bad, "stereo matches do not link camera 1 and 2 both ways")
    # without a two-camera keyframe the file stays schema version 1
    assert save_atlas(build_atlas(place), tmp_path / "plain.slamkit").schema_version == mapfile.SCHEMA_VERSION


def test_read_atlas_for_tools(tmp_path: Path, place: DbowPlaceRecognizer) -> None:
    atlas = build_atlas(place)
    save_atlas(atlas, tmp_path / "m.slamkit", config={"map": {"covisibility_min_shared": 15}})
    assert_same_atlas(atlas, mapfile.read_atlas(tmp_path / "m.slamkit"))


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


def assert_same_frames(a: FrameRecords, b: FrameRecords) -> None:
    for name in ("t_s", "frame_index", "ref_kf_id", "T_c_r"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        assert getattr(a, name).dtype == getattr(b, name).dtype, name


def test_round_trip_keeps_the_sessions_frames(tmp_path: Path, place: DbowPlaceRecognizer) -> None:
    """The frames a runner hands ``save_atlas`` (each relative to a keyframe of its map) come back bit for bit as the
    loaded Atlas's ``loaded_frames`` (what a later session's trajectory starts from), map by map; the map contents are
    the same as without them; a frame whose reference keyframe is not in the map is left out."""
    atlas = build_atlas(place)
    frames = build_frames(atlas)
    stray = frames[0]
    frames[0] = FrameRecords(  # one more frame, relative to a keyframe id that is in no map
        np.append(stray.t_s, 99.0), np.append(stray.frame_index, 99), np.append(stray.ref_kf_id, 10_000),
        np.concatenate([stray.T_c_r, np.eye(4)[None]]),
    )  # fmt: skip
    path = tmp_path / "frames.slamkit"
    info = save_atlas(atlas, path, frames=frames)
    assert info.n_frames == map_file_info(path).n_frames == len(stray) + len(frames[1])
    loaded = load_atlas(path, new_store, DbowPlaceRecognizer())
    assert_same_atlas(atlas, loaded)
    assert sorted(loaded.loaded_frames) == [0, 1]
    assert_same_frames(loaded.loaded_frames[0], stray)
    assert_same_frames(loaded.loaded_frames[1], frames[1])
    # saved again from the loaded Atlas with the frames it loaded: the same frames
    again = tmp_path / "again.slamkit"
    save_atlas(loaded, again, frames=loaded.loaded_frames)
    reloaded = load_atlas(again, new_store, DbowPlaceRecognizer())
    for map_id in (0, 1):
        assert_same_frames(reloaded.loaded_frames[map_id], loaded.loaded_frames[map_id])
    # saved with no frames: every map has none
    none = tmp_path / "none.slamkit"
    save_atlas(atlas, none)
    assert map_file_info(none).n_frames == 0
    assert all(len(f) == 0 for f in load_atlas(none, new_store, DbowPlaceRecognizer()).loaded_frames.values())


def _members(path: Path) -> list[tuple[str, np.ndarray]]:
    with zipfile.ZipFile(path) as zf:
        return [(n, np.load(zf.open(n), allow_pickle=False)) for n in zf.namelist() if n.endswith(".npy")]


def test_a_file_written_before_it_kept_frames_loads_with_none(tmp_path: Path, place: DbowPlaceRecognizer) -> None:
    """Schema 1 as written before the ``fr_*`` members: no ``frames`` in the manifest's map entries, no members."""
    atlas = build_atlas(place)
    path = tmp_path / "new.slamkit"
    save_atlas(atlas, path, frames=build_frames(atlas))
    manifest = mapfile.read_manifest(path)
    for meta in manifest["maps"]:
        del meta["frames"]
    old = tmp_path / "old.slamkit"
    mapfile._write(old, manifest, [(n, a) for n, a in _members(path) if "/fr_" not in n], mapfile.SCHEMA_VERSION)
    loaded = load_atlas(old, new_store, DbowPlaceRecognizer())
    assert_same_atlas(atlas, loaded)
    assert loaded.loaded_frames == {} and map_file_info(old).n_frames == 0


@pytest.mark.parametrize(
    ("member", "change", "match"),
    [
        ("m0/fr_ref_kf.npy", lambda a: a + 10_000, "reference keyframe 100"),
        ("m1/fr_T_c_r.npy", lambda a: a * np.nan, "not finite"),
        ("m1/fr_T_c_r.npy", lambda a: a + 1.0, "last row"),
        ("m0/fr_t_s.npy", lambda a: a[:-1], "fr_t_s is"),
    ],
)
def test_bad_frames_load_nothing(
    tmp_path: Path, place: DbowPlaceRecognizer, member: str, change: Any, match: str
) -> None:
    """Frames behind a valid checksum that do not fit the map: a MapFileError naming the file, nothing loaded."""
    atlas = build_atlas(place)
    path = tmp_path / "m.slamkit"
    save_atlas(atlas, path, frames=build_frames(atlas))
    members = [(n, change(a) if n == member else a) for n, a in _members(path)]
    bad = tmp_path / "bad.slamkit"
    mapfile._write(bad, mapfile.read_manifest(path), members, mapfile.SCHEMA_VERSION)
    refused(bad, match)


# ---- bad input: a clear error naming the file, nothing loaded --------------------------------------------------


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
    manifest["schema_version"] = mapfile.RIG_SCHEMA_VERSION + 1
    with zipfile.ZipFile(saved) as zf:
        members = [(n, np.load(zf.open(n), allow_pickle=False)) for n in zf.namelist() if n.endswith(".npy")]
    future = tmp_path / "future.slamkit"
    mapfile._write(future, manifest, members, mapfile.RIG_SCHEMA_VERSION + 1)
    err = refused(future, "schema version 3")
    assert "reads schema versions 1, 2" in str(err)


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


def test_map_info_command(saved: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from slamkit.cli import main

    assert main(["map", "info", str(saved)]) == 0
    out = capsys.readouterr().out
    info = map_file_info(saved)
    assert f"schema version  {mapfile.SCHEMA_VERSION}" in out
    assert f"{info.n_keyframes} keyframes, {info.n_points} points" in out
    assert f"{info.size_bytes} bytes" in out
    assert "(active)" in out
    assert main(["map", "info", "--json", str(saved)]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["maps"] == [{"id": m, "keyframes": k, "points": p} for m, k, p in info.maps]
    run_dir = saved.parent / "run"
    run_dir.mkdir()
    (run_dir / "map.slamkit").write_bytes(saved.read_bytes())
    assert main(["map", "info", str(run_dir)]) == 0 and str(run_dir / "map.slamkit") in capsys.readouterr().out
    saved.write_bytes(saved.read_bytes()[:-3])
    assert main(["map", "info", str(saved)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("slamkit map: map file ") and str(saved) in err and "truncated" in err


# ---- map.save / map.load in a run (slamkit/map/mapfile_run.py) ------------------------------------------------


def test_map_save_keys_and_store_node(tmp_path: Path) -> None:
    from slamkit.map import mapfile_run

    node = {
        "_target_": "slamkit.map.store.InMemoryMapStore",
        "covisibility_min_shared": 15,
        "save": None,
        "load": None,
        "session_start": "new_map",
    }
    assert mapfile_run.store_node(node) == {
        "_target_": "slamkit.map.store.InMemoryMapStore",
        "covisibility_min_shared": 15,
    }
    # map.session_start: how a session on a loaded Atlas starts (docs/atlas.md "Multi-session")
    assert mapfile_run.session_start(node) == "new_map"
    assert mapfile_run.session_start({}) == "reloc_or_new_map"
    with pytest.raises(ConfigError, match=r"map\.session_start"):
        mapfile_run.session_start({"session_start": "resume"})
    assert mapfile_run.save_path(node, tmp_path) is None
    assert mapfile_run.save_path({"save": True}, tmp_path) == tmp_path / "map.slamkit"
    assert mapfile_run.save_path({"save": "x/m.slamkit"}, tmp_path) == Path("x/m.slamkit")


def test_a_run_that_fails_late_saves_its_map_and_one_that_fails_early_leaves_the_file(
    tmp_path: Path, place: DbowPlaceRecognizer
) -> None:
    from slamkit.map import mapfile_run

    target = tmp_path / "m.slamkit"
    atlas = build_atlas(place)
    with (
        pytest.raises(RuntimeError, match="late"),
        mapfile_run.saving_map({"save": str(target)}, atlas, tmp_path, None),
    ):
        raise RuntimeError("failed late")
    assert map_file_info(target).n_keyframes == sum(s.n_keyframes() for _, s in atlas.items())
    before = target.read_bytes()
    empty = Atlas(new_store, None)
    with (
        pytest.raises(RuntimeError, match="early"),
        mapfile_run.saving_map({"save": str(target)}, empty, tmp_path, None),
    ):
        raise RuntimeError("failed early")
    assert target.read_bytes() == before
    # a run that ends normally with an unwritable map.save: the save's error is the run's
    with (
        pytest.raises(MapFileError, match="cannot be written"),
        mapfile_run.saving_map({"save": str(target / "sub" / "m.slamkit")}, atlas, tmp_path, None),
    ):
        pass
