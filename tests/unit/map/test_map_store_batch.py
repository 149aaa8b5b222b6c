"""The store's batched writes (add_points, add_observations, and map_points' forms of them for a store without) leave
the very map the one-at-a-time writes leave, and local mapping's choice of the triangulated pairs that get a point (``_free_pairs``) is the one-after-the-other rule."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from slamkit.features import Features, Observations
from slamkit.geometry.camera import PinholeCamera
from slamkit.map.entities import KeyFrame, MapPoint
from slamkit.map.point_table import COUNTERS, SYNCED_ATTRIBUTES
from slamkit.map.store import InMemoryMapStore
from slamkit.pipeline import map_points
from slamkit.pipeline.local_mapping import _free_pairs

CAMERA = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)
N = 40


def _features(rng: np.random.Generator, stereo: bool) -> Observations:
    uv = rng.uniform(0, 480, (N, 2)).astype(np.float32)
    feats = Observations.monocular(
        Features(
            uv,
            uv,
            rng.integers(0, 8, N).astype(np.int32),
            np.zeros(N, np.float32),
            np.zeros(N, np.float32),
            rng.integers(0, 256, (N, 32), dtype=np.uint8),
            1.2,
            8,
        ),
        CAMERA.unproject_image(uv.astype(np.float64)),
    )
    if stereo:  # half the keypoints with a right coordinate: their observations weigh 2 (ORB-SLAM2 nObs += 2)
        u_right = np.where(rng.random(N) < 0.5, uv[:, 0] - 20.0, np.nan).astype(np.float32)
        feats = dataclasses.replace(feats, u_right_px=u_right, depth_m=np.full(N, 2.0, np.float32), bf=40.0)
    return feats


def _store(seed: int, stereo: bool) -> InMemoryMapStore:
    rng = np.random.default_rng(seed)
    store = InMemoryMapStore()
    for _ in range(3):
        kf_id = store.new_keyframe_id()
        store.add_keyframe(
            KeyFrame(kf_id, kf_id, float(kf_id), np.eye(4), CAMERA, _features(rng, stereo), np.full(N, -1, np.int64))
        )
    return store


def _points(store: InMemoryMapStore, seed: int, count: int) -> list[MapPoint]:
    rng = np.random.default_rng(100 + seed)
    return [
        MapPoint(store.new_point_id(), rng.normal(size=3), rng.integers(0, 256, 32, dtype=np.uint8), 0, 0)
        for _ in range(count)
    ]


def _state(store: InMemoryMapStore) -> dict[str, Any]:
    """Everything the writes touch: each point's attributes and observations (in insertion order), each keyframe's
    point ids, and the point table's rows and counters."""
    ids = np.array(store.point_ids(), np.int64)
    out: dict[str, Any] = {
        "points": [
            (p.id, p.xyz_w.tolist(), p.descriptor.tolist(), p.normal_w.tolist(), p.d_min_m, p.d_max_m)
            for p in store.get_points(ids.tolist())
        ],
        "observations": [list(store.get_point(pid).observations.items()) for pid in ids.tolist()],
        "keyframes": [store.get_keyframe(k).point_ids.tolist() for k in store.keyframe_ids()],
    }
    for name in [*(n for n, _, _ in SYNCED_ATTRIBUTES), *COUNTERS]:
        out[name] = store.point_rows(ids, name).tolist()
    return out


class _OneAtATime:
    """A store without the batched methods (as the MapStore protocol allows): map_points' helpers fall back."""

    def __init__(self, store: InMemoryMapStore) -> None:
        self.add_point = store.add_point
        self.add_observation = store.add_observation


@pytest.mark.parametrize("stereo", [False, True])
@pytest.mark.parametrize("helpers", [False, True])
def test_batched_writes_leave_the_map_of_the_one_at_a_time_writes(stereo: bool, helpers: bool) -> None:
    """helpers: through map_points.add_points / add_observations, for one store with and one without the batches."""
    one, batch = _store(0, stereo), _store(0, stereo)
    rng = np.random.default_rng(1)
    f0, f1 = rng.permutation(N)[:12], rng.permutation(N)[:12]
    for store, batched in ((one, False), (batch, True)):
        points = _points(store, 0, 12)
        pids = np.array([p.id for p in points], np.int64)
        if helpers:
            target: Any = store if batched else _OneAtATime(store)
            map_points.add_points(target, points)
            map_points.add_observations(target, pids, 0, f0)
            map_points.add_observations(target, pids, 1, f1)
        elif batched:
            store.add_points(points)
            store.add_observations(pids, 0, f0)
            store.add_observations(pids, 1, f1)
        else:
            for point in points:
                store.add_point(point)
            for pid, a, b in zip(pids.tolist(), f0.tolist(), f1.tolist(), strict=True):
                store.add_observation(pid, 0, a)
                store.add_observation(pid, 1, b)
    assert _state(one) == _state(batch)
    assert batch.point_rows(np.array(batch.point_ids()), "n_observations").tolist() == [2] * 12
    if stereo:  # the weights of a stereo keyframe's keypoints were read: some observations count twice
        assert max(batch.point_rows(np.array(batch.point_ids()), "n_observations_orbslam").tolist()) > 2


@pytest.mark.parametrize("stereo", [False, True])
def test_add_observations_follows_the_general_rule_for_repeats_and_known_observers(stereo: bool) -> None:
    """A point listed twice, a feature listed twice, a point already observing the keyframe (at another keypoint):
    the one-at-a-time rule, in order."""
    one, batch = _store(2, stereo), _store(2, stereo)
    for store in (one, batch):
        points = _points(store, 2, 4)
        store.add_points(points)
        store.add_observation(points[3].id, 0, 30)
    cases = [
        (np.array([0, 1, 0]), np.array([1, 2, 3])),  # point 0 twice: its second keypoint wins
        (np.array([1, 2]), np.array([5, 5])),  # keypoint 5 twice: the later point holds it
        (np.array([3, 2]), np.array([7, 8])),  # point 3 observes keyframe 0 already (keypoint 30)
    ]
    for k, (rows, feats) in enumerate(cases):
        kf = k % 2
        pids = np.array(one.point_ids(), np.int64)[rows]
        for pid, feat in zip(pids.tolist(), feats.tolist(), strict=True):
            one.add_observation(pid, kf + 1 if k == 1 else kf, feat)
        batch.add_observations(pids, kf + 1 if k == 1 else kf, feats)
        assert _state(one) == _state(batch)


def test_add_points_refuses_all_or_nothing() -> None:
    store = _store(3, False)
    points = _points(store, 3, 3)
    store.add_points(points[:1])
    before = _state(store)
    with pytest.raises(ValueError, match="already in the map"):
        store.add_points([points[1], points[0]])
    twin = MapPoint(points[2].id, np.zeros(3), np.zeros(32, np.uint8), 0, 0)
    with pytest.raises(ValueError, match="share an id"):
        store.add_points([points[2], twin])
    with pytest.raises(ValueError, match="not issued"):
        store.add_points([MapPoint(10_000, np.zeros(3), np.zeros(32, np.uint8), 0, 0)])
    store.remove_point(points[0].id)
    with pytest.raises(ValueError, match="erased"):
        store.add_points([points[1], MapPoint(points[0].id, np.zeros(3), np.zeros(32, np.uint8), 0, 0)])
    assert store.point_ids() == [] and not store.has_point(points[1].id)
    assert before["keyframes"] == _state(store)["keyframes"]


def _reference_free_pairs(kf1: Any, kf2: Any, i1: np.ndarray, i2: np.ndarray) -> list[int]:
    """Local mapping's former loop: each pair in turn, with the keyframes' point ids updated after each point."""
    own1, own2 = kf1.point_ids.copy(), kf2.point_ids.copy()

    def partner(kf: Any, own: np.ndarray, idx: int) -> bool:
        sm = kf.features.stereo_match
        return sm is not None and sm[idx] >= 0 and own[sm[idx]] >= 0

    rig = kf1.features.two_cameras or kf2.features.two_cameras
    keep = []
    for m, (a, b) in enumerate(zip(i1.tolist(), i2.tolist(), strict=True)):
        if own1[a] >= 0 or own2[b] >= 0:
            continue
        if rig and (partner(kf1, own1, a) or partner(kf2, own2, b)):
            continue
        own1[a] = own2[b] = 1_000 + m
        keep.append(m)
    return keep


def _fake_keyframe(rng: np.random.Generator, rig: bool) -> Any:
    point_ids = np.where(rng.random(N) < 0.3, rng.integers(0, 100, N), -1)
    stereo_match = None
    if rig:  # keypoints 0..N/2 (camera 1) paired with some of N/2..N (camera 2) and back
        stereo_match = np.full(N, -1, np.int64)
        left = rng.permutation(N // 2)[: N // 4]
        right = N // 2 + rng.permutation(N // 2)[: N // 4]
        stereo_match[left], stereo_match[right] = right, left
    return SimpleNamespace(point_ids=point_ids, features=SimpleNamespace(two_cameras=rig, stereo_match=stereo_match))


@pytest.mark.parametrize("rig", [False, True])
@pytest.mark.parametrize("seed", range(6))
def test_free_pairs_is_the_one_after_the_other_rule(seed: int, rig: bool) -> None:
    rng = np.random.default_rng(seed)
    kf1, kf2 = _fake_keyframe(rng, rig), _fake_keyframe(rng, rig)
    distinct = seed % 2 == 0 and not rig
    i1 = rng.permutation(N)[:25] if distinct else rng.integers(0, N, 30)  # repeats: the first free one wins
    i2 = rng.permutation(N)[:25] if distinct else rng.integers(0, N, 30)
    got = _free_pairs(kf1, kf2, i1, i2).tolist()
    assert got == _reference_free_pairs(kf1, kf2, i1, i2)
    assert got and len(got) < i1.size  # some pairs taken, some refused


def test_assign_points_writes_the_changed_rows_and_every_point_holds_its_row() -> None:
    """Points whose value is unchanged bit for bit keep theirs; the others (a value changed, -0.0 for 0.0) get the
    new one; every point's attribute equals its table row afterwards, and the counters of a replaced point add up."""
    store = _store(4, False)
    points = _points(store, 4, 5)
    store.add_points(points)
    pids = np.array([p.id for p in points], np.int64)
    normals = np.zeros((5, 3))
    normals[:, 2] = 1.0
    store.assign_points(pids, "normal_w", normals)
    kept = store.get_point(int(pids[0])).normal_w
    update = normals.copy()
    update[1, 2] = 0.5
    update[2, 0] = -0.0  # the same number, another bit pattern: written
    store.assign_points(pids, "normal_w", update)
    assert store.get_point(int(pids[0])).normal_w is kept
    for pid, row in zip(pids.tolist(), update, strict=True):
        value = store.get_point(pid).normal_w
        assert value.tobytes() == row.tobytes() and not value.flags.writeable
    assert np.signbit(store.get_point(int(pids[2])).normal_w[0])
    store.assign_points(pids, "d_max_m", np.array([1.0, 2.0, 3.0, 4.0, 5.0]))
    store.assign_points(pids, "d_max_m", np.array([1.0, 2.5, 3.0, np.nan, 5.0]))
    d_max = [store.get_point(pid).d_max_m for pid in pids.tolist()]
    assert d_max[:3] == [1.0, 2.5, 3.0] and np.isnan(d_max[3]) and type(d_max[0]) is float
    np.testing.assert_array_equal(store.point_rows(pids, "d_max_m"), np.array(d_max))
    store.increase_visible(pids[:2], 3)
    store.increase_found(pids[:1], 2)
    store.replace_point(int(pids[0]), int(pids[1]))
    assert store.point_rows(pids[1:2], "n_visible").tolist() == [8] and store.point_rows(
        pids[1:2], "n_found"
    ).tolist() == [4]


@pytest.mark.parametrize("stereo", [False, True])
def test_add_keyframe_observes_each_named_point_once(stereo: bool) -> None:
    """A new keyframe's point ids: a point in the map is observed by the first feature naming it; a second feature
    naming it, a point erased and an id never used become -1 (the per-feature rule of add_keyframe)."""
    store = _store(5, stereo)
    points = _points(store, 5, 6)
    store.add_points(points)
    pids = [p.id for p in points]
    for pid in pids:
        store.add_observation(pid, 0, pid % N)
    store.remove_point(pids[5])
    own = np.full(N, -1, np.int64)
    own[[3, 4, 9, 10, 11, 20, 30]] = [pids[0], pids[1], pids[0], pids[5], 99_999, pids[2], pids[1]]
    rng = np.random.default_rng(6)
    kf_id = store.new_keyframe_id()
    store.add_keyframe(KeyFrame(kf_id, kf_id, 0.0, np.eye(4), CAMERA, _features(rng, stereo), own))
    got = store.get_keyframe(kf_id).point_ids
    expected = np.full(N, -1, np.int64)
    expected[[3, 4, 20]] = [pids[0], pids[1], pids[2]]
    np.testing.assert_array_equal(got, expected)
    feats = store.get_keyframe(kf_id).features
    for feat, pid in ((3, pids[0]), (4, pids[1]), (20, pids[2])):
        assert list(store.get_point(pid).observations.items())[-1] == (kf_id, feat)
        weight = 2 if stereo and np.isfinite(feats.u_right_px[feat]) else 1
        first = 2 if stereo and np.isfinite(store.get_keyframe(0).features.u_right_px[pid % N]) else 1
        assert store.point_rows(np.array([pid]), "n_observations").tolist() == [2]
        assert store.point_rows(np.array([pid]), "n_observations_orbslam").tolist() == [first + weight]
    assert store.point_rows(np.array([pids[3]]), "n_observations").tolist() == [1]
