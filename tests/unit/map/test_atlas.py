"""The Atlas (ORB-SLAM3): several maps with ids unique across them, the active one, a keyframe database across
maps, resets and new maps; and the lost policy that chooses between them."""

from __future__ import annotations

import numpy as np
import pytest
from slamkit_dbow.recognizer import DbowPlaceRecognizer

from slamkit.errors import ConfigError, SlamkitError
from slamkit.features import Features, Observations
from slamkit.geometry.camera import PinholeCamera
from slamkit.interfaces import MapStore
from slamkit.io.synthetic.dataset import SyntheticDataset
from slamkit.map.atlas import Atlas, MapChange
from slamkit.map.entities import KeyFrame, MapPoint
from slamkit.map.ids import IdAllocator
from slamkit.map.store import InMemoryMapStore
from slamkit.pipeline.lost import LostDecision, LostPolicy, LostRecord, decide_when_lost

CAMERA = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)
N_FEATS = 60


def _features(descriptors: np.ndarray) -> Observations:
    n = descriptors.shape[0]
    feats = Features(
        uv_px=np.zeros((n, 2), np.float32),
        uv_undist_px=np.zeros((n, 2), np.float32),
        level=np.zeros(n, np.int32),
        angle_deg=np.zeros(n, np.float32),
        response=np.zeros(n, np.float32),
        descriptors=descriptors,
        scale_factor=1.2,
        n_levels=8,
    )
    return Observations.monocular(feats, CAMERA.unproject_image(feats.uv_undist_px.astype(np.float64)))


def _add_keyframe(store: MapStore, descriptors: np.ndarray | None = None) -> int:
    desc = np.zeros((N_FEATS, 32), np.uint8) if descriptors is None else descriptors
    kf_id = store.new_keyframe_id()
    with store.write():
        store.add_keyframe(
            KeyFrame(kf_id, kf_id, float(kf_id), np.eye(4), CAMERA, _features(desc), np.full(len(desc), -1, np.int64))
        )
    return kf_id


def _share_points(store: MapStore, kf_ids: list[int], count: int, first_feature: int = 0) -> list[int]:
    """``count`` points seen by every keyframe of kf_ids (features first_feature.. of each)."""
    pids = []
    with store.write():
        for i in range(count):
            pid = store.new_point_id()
            store.add_point(MapPoint(pid, np.zeros(3), np.zeros(32, np.uint8), kf_ids[0], kf_ids[0]))
            for k in kf_ids:
                store.add_observation(pid, k, first_feature + i)
            pids.append(pid)
        for k in kf_ids:
            store.update_connections(k)
    return pids


def _atlas(place: DbowPlaceRecognizer | None = None) -> Atlas:
    return Atlas(lambda ids: InMemoryMapStore(15, ids=ids), place)


def test_ids_are_unique_across_maps_and_a_new_map_keeps_the_old_one() -> None:
    atlas = _atlas()
    first = atlas.active
    a = [_add_keyframe(first) for _ in range(3)]
    pa = _share_points(first, a, 20)
    assert atlas.create_map() == 1 and atlas.active_id == 1 and atlas.map_ids() == [0, 1]
    second = atlas.active
    assert second is not first and second.ids is first.ids is atlas.ids
    b = [_add_keyframe(second) for _ in range(3)]
    pb = _share_points(second, b, 20)
    assert not set(a) & set(b) and not set(pa) & set(pb), "ids unique across maps"
    # the old map is kept as it was
    assert first.keyframe_ids() == a and first.n_points() == 20
    assert atlas.change_since(0) == MapChange.NEW_MAP and atlas.change_since(1) is None
    assert [atlas.map_of(k) for k in a + b] == [0, 0, 0, 1, 1, 1] and atlas.map_of(10**6) is None
    assert atlas.keyframes_outside_active() == set(a)


def test_neighbours_come_from_each_keyframe_own_map() -> None:
    atlas = _atlas()
    a = [_add_keyframe(atlas.active) for _ in range(3)]
    _share_points(atlas.active, a, 20)
    atlas.create_map()
    b = [_add_keyframe(atlas.active) for _ in range(2)]
    _share_points(atlas.active, b, 30)
    # a keyframe of the old map is grouped with its own covisible keyframes, not the active map's
    assert atlas.best_neighbors(a[0], 10) == [a[1], a[2]]
    assert atlas.best_neighbors(b[0], 10) == [b[1]]
    assert atlas.active.covisibility.best_neighbors(a[0], 10) == []


def test_reset_erases_the_active_map_and_its_keyframe_database_entries_only() -> None:
    place = DbowPlaceRecognizer("builtin")
    atlas = _atlas(place)
    rng = np.random.default_rng(0)

    def described_keyframe() -> int:
        desc = rng.integers(0, 256, (N_FEATS, 32), dtype=np.uint8)
        kf_id = _add_keyframe(atlas.active, desc)
        place.add(kf_id, place.transform(desc))
        return kf_id

    a = [described_keyframe() for _ in range(3)]
    atlas.create_map()
    b = [described_keyframe() for _ in range(3)]
    _share_points(atlas.active, b, 20)
    # one keyframe database across maps
    assert set(place.database.keyframe_ids()) == set(a + b)
    kept = atlas.active
    assert atlas.reset_active() == 2 and atlas.map_ids() == [0, 2]
    assert atlas.active is kept and kept.n_keyframes() == 0 and kept.n_points() == 0
    assert atlas.change_since(1) == MapChange.RESET
    assert set(place.database.keyframe_ids()) == set(a), "the other map's keyframes stay in the database"
    assert atlas.get(0).keyframe_ids() == a
    # new ids after the reset are still unique across maps
    assert _add_keyframe(atlas.active) > max(a + b)


def test_a_store_that_ignores_the_shared_ids_is_refused() -> None:
    with pytest.raises(ConfigError, match="ids unique across"):
        Atlas(lambda ids: InMemoryMapStore(15, ids=IdAllocator()))


def test_an_atlas_of_one_given_map_cannot_start_another() -> None:
    store = InMemoryMapStore()
    atlas = Atlas.of(store)
    assert atlas.active is store and atlas.ids is store.ids
    with pytest.raises(SlamkitError, match="cannot start another map"):
        atlas.create_map()


@pytest.mark.parametrize(
    ("keyframes", "lost_for_s", "expected"),
    [
        (2, 0.0, LostDecision.RESET_MAP),
        (10, 0.0, LostDecision.RESET_MAP),  # ORB-SLAM3: KeyFramesInMap() <= 10 -> ResetActiveMap
        (10, 60.0, LostDecision.RESET_MAP),
        (11, 0.0, LostDecision.RELOCALIZE),  # RECENTLY_LOST: relocalize in the active map
        (11, 3.0, LostDecision.RELOCALIZE),  # mTimeStamp - mTimeStampLost > 3.0f: not yet
        (11, 3.04, LostDecision.NEW_MAP),  # lost for good: CreateMapInAtlas
        (500, 100.0, LostDecision.NEW_MAP),
    ],
)
def test_the_lost_policy_is_orbslam3s(keyframes: int, lost_for_s: float, expected: LostDecision) -> None:
    assert decide_when_lost(LostRecord(keyframes, lost_for_s), LostPolicy(10, 3.0)) == expected


def test_the_lost_policy_reads_its_constants() -> None:
    assert decide_when_lost(LostRecord(11, 1.0), LostPolicy(20, 3.0)) == LostDecision.RESET_MAP
    assert decide_when_lost(LostRecord(11, 1.0), LostPolicy(10, 0.5)) == LostDecision.NEW_MAP


def test_skip_makes_a_time_jump() -> None:
    """The acceptance runs rely on ``dataset.skip`` keeping the raw timestamps (the lost time is sequence time)."""
    ds = SyntheticDataset(scene="room", skip=[10, 99], max_frames=12)
    assert ds[10].timestamp_s == pytest.approx(100 / 30.0)
