"""Fusion's compiled helpers and its gathers agree with the numpy expressions they replace."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slamkit.geometry.camera import PinholeCamera
from slamkit.map.entities import MapPoint
from slamkit.map.store import InMemoryMapStore
from slamkit.pipeline.frame import ImageBounds
from slamkit.pipeline.fusion import absent_from
from slamkit.pipeline.map_points import refresh_points, unique_point_ids
from slamkit.pipeline.projection import frustum_test


@pytest.mark.parametrize("seed", range(5))
def test_absent_from_is_not_in_the_own_points(seed: int) -> None:
    rng = np.random.default_rng(seed)
    own = np.where(rng.random(300) < 0.4, rng.integers(0, 5_000, 300), -1)
    ids = rng.integers(-2, 6_000, 400)
    got = absent_from(ids, own)
    np.testing.assert_array_equal(got, ~np.isin(ids, own[own >= 0]))
    assert got.any() and not got.all()


def test_absent_from_without_own_points_keeps_every_id() -> None:
    ids = np.arange(10, dtype=np.int64)
    assert absent_from(ids, np.full(5, -1, np.int64)).all()
    assert absent_from(np.zeros(0, np.int64), np.arange(3, dtype=np.int64)).shape == (0,)
    read_only = np.arange(3, dtype=np.int64)
    read_only.setflags(write=False)  # a keyframe's point_ids view
    np.testing.assert_array_equal(absent_from(ids, read_only), ids >= 3)


@pytest.mark.parametrize("seed", range(3))
def test_unique_point_ids_is_numpy_unique_of_the_ids(seed: int) -> None:
    rng = np.random.default_rng(seed)
    parts = [np.where(rng.random(200) < 0.5, rng.integers(0, 3_000, 200), -1) for _ in range(6)]
    expected = np.unique(np.concatenate(parts))
    got = unique_point_ids(parts)
    assert got.dtype == np.int64
    np.testing.assert_array_equal(got, expected[expected >= 0])
    assert unique_point_ids([]).size == 0 and unique_point_ids([np.full(4, -1, np.int64)]).size == 0


class _NumpyPinhole(PinholeCamera):
    """A pinhole camera whose projection is not PinholeCamera.project_image itself: frustum_test's general path."""

    def project_image(self, xyz_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return super().project_image(xyz_c)


@pytest.mark.parametrize("seed", range(4))
def test_pinhole_frustum_kernel_is_the_numpy_frustum_test_bit_for_bit(seed: int) -> None:
    rng = np.random.default_rng(seed)
    args = (640, 480, 517.3, 516.5, 318.6, 255.3, (0.26, -0.95, -0.005, 0.002, 1.16))
    fast, general = PinholeCamera(*args), _NumpyPinhole(*args)
    bounds = ImageBounds.of(fast)
    n = 3_000
    xyz = rng.normal(size=(n, 3)) * 2.0 + np.array([0.0, 0.0, 1.5])
    xyz[:5] = 0.0  # at the camera centre: zero depth and distance
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    d_max = rng.uniform(0.5, 6.0, n)
    d_min = d_max / 1.2**7
    d_max[10:20] = np.nan  # points without a reference observation
    a = rng.normal(size=3) * 0.2
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(a).as_matrix()
    T[:3, 3] = rng.normal(size=3) * 0.1
    got = frustum_test(T, fast, bounds, xyz, normal, d_min, d_max, 0.5, 1.2, 8)
    want = frustum_test(T, general, bounds, xyz, normal, d_min, d_max, 0.5, 1.2, 8)
    assert 0 < got.visible.sum() < n
    for name in ("visible", "uv_px", "predicted_level", "view_cos", "z_m"):
        g, w = np.ascontiguousarray(getattr(got, name)), np.ascontiguousarray(getattr(want, name))
        assert g.shape == w.shape and g.dtype == w.dtype, name
        np.testing.assert_array_equal(g.view(np.uint8), w.view(np.uint8), err_msg=name)  # same bits (NaNs too)


class _OneAtATime:
    """A store seen through the MapStore protocol alone: without the in-memory store's ``add_observations``, so
    fusion takes its loop over the matches (a third-party store's path)."""

    def __init__(self, store: InMemoryMapStore) -> None:
        self._store = store

    def __getattr__(self, name: str) -> Any:
        if name == "add_observations":
            raise AttributeError(name)
        return getattr(self._store, name)


def _fusion_scene() -> tuple[InMemoryMapStore, list[int], int]:
    """Five keyframes; points 0..99 seen by kf0 and kf1 at feature j. kf4 holds at feature j: for j in 20..39 a
    duplicate seen by three keyframes (it wins a merge), for j in 40..59 one seen by two (it loses), for 60..64 point j
    itself; features 0..19 and 65..99 are free. -> (store, the candidates (kf0's points), kf4's id)."""
    from tests.unit.pipeline.test_local_mapping_step import keyframe, scene

    xyz, desc = scene(3)
    store = InMemoryMapStore()
    rng = np.random.default_rng(3)
    # each keyframe's descriptors a few bits off the scene's (within the 50-bit threshold): merges change medians
    kfs = [
        keyframe(store, x, xyz, desc ^ (rng.random(desc.shape) < 0.02).astype(np.uint8))
        for x in (0.0, 0.1, 0.2, 0.3, 0.4)
    ]
    for kf in kfs:
        store.add_keyframe(kf)
    for j in range(100):
        pid = store.new_point_id()
        store.add_point(MapPoint(pid, xyz[j].copy(), desc[j].copy(), kfs[0].id, kfs[0].id))
        for k in (0, 1, 4) if 60 <= j < 65 else (0, 1):
            store.add_observation(pid, kfs[k].id, j)
    for j in range(20, 60):
        pid = store.new_point_id()
        store.add_point(MapPoint(pid, xyz[j].copy(), desc[j].copy(), kfs[4].id, kfs[4].id))
        for k in (4, 2, 3) if j < 40 else (4, 3):
            store.add_observation(pid, kfs[k].id, j)
    refresh_points(store, store.point_ids())
    own = kfs[0].point_ids
    return store, own[own >= 0].tolist(), kfs[4].id


def _map_state(store: InMemoryMapStore) -> list[Any]:
    """Everything fusion may change, in comparable form (observations with their insertion order)."""
    pids = np.array(store.point_ids(), np.int64)
    state: list[Any] = [pids.tolist()]
    state += [list(store.get_point(p).observations.items()) for p in pids.tolist()]
    state += [store.get_keyframe(k).point_ids.tolist() for k in store.keyframe_ids()]
    for name in ("descriptor", "xyz_w", "n_visible", "n_found", "n_observations", "n_observations_orbslam"):
        state.append(store.point_rows(pids, name).tolist())
    return state


def _count_batches(store: InMemoryMapStore, sizes: list[int]) -> None:
    """Record the size of every ``store.add_observations`` call in ``sizes``."""
    original = store.add_observations

    def add(point_ids: np.ndarray, keyframe_id: int, feature_indices: np.ndarray) -> None:
        sizes.append(len(point_ids))
        original(point_ids, keyframe_id, feature_indices)

    setattr(store, "add_observations", add)  # noqa: B010 - an instance attribute over the method


def test_batched_fusion_is_the_loop_over_the_matches() -> None:
    """The in-memory store's batch of new observations (fusion into a one-camera keyframe) leaves the map the loop
    over the matches leaves: the same merges both ways, the same new observations, descriptors and counters."""
    from slamkit.pipeline.fusion import fuse_points

    results = []
    for wrap in (False, True):
        store, candidates, target = _fusion_scene()
        seen = _OneAtATime(store) if wrap else store
        batches: list[int] = []
        _count_batches(store, batches)
        fused = fuse_points(seen, store.get_keyframe(target), candidates, 3.0, max_distance=50, chi2_gate=5.991)
        results.append((fused, _map_state(store)))
        assert batches == ([] if wrap else [55])  # the 55 free features in one batch (the loop adds one at a time)
    (fused, batched), (fused_loop, looped) = results
    assert fused == fused_loop == 95  # 55 free features, 20 + 20 merges; points 60..64 are kf4's already
    assert batched == looped
    store, candidates, target = _fusion_scene()
    fuse_points(store, store.get_keyframe(target), candidates, 3.0, max_distance=50, chi2_gate=5.991)
    assert store.n_points() == 100  # the 40 duplicates merged away


def test_survivors_left_to_the_keyframes_refresh_get_the_same_descriptors() -> None:
    """refresh_survivors=False, then the refresh of every point the keyframe observes (local mapping's order): the
    map of refreshing each merge's survivor at once, then the same refresh. Without that refresh the survivors that
    took a point's observations may keep a stale descriptor: the flag hands the caller a real duty."""
    from slamkit.pipeline.fusion import fuse_points

    states = []
    for refresh in (True, False):
        store, candidates, target = _fusion_scene()
        kf = store.get_keyframe(target)
        fuse_points(store, kf, candidates, 3.0, max_distance=50, chi2_gate=5.991, refresh_survivors=refresh)
        if not refresh:
            stale = _map_state(store)
        refresh_points(store, kf.point_ids[kf.point_ids >= 0].tolist())
        states.append(_map_state(store))
    assert states[0] == states[1]
    assert stale != states[1]
