"""Local mapping's observation gathers (issue 15: no Python loop per observation) give exactly the rows of the
per-point loops they replace: the local BA snapshot lists every observation of its points by its keyframes in
point order then keyframe-id order (the order decides the optimizer's floating-point sums, so the trajectory), with
the right pose rows, pixels and levels, whatever order the observations were added in."""

from __future__ import annotations

import numpy as np
import pytest

from slamkit.map.entities import MapPoint
from slamkit.map.store import InMemoryMapStore
from slamkit.pipeline.bundle import snapshot_bundle
from slamkit.pipeline.map_points import (
    flat_observations,
    gather_observations,
    refresh_points,
    sorted_observations,
    unique_point_ids,
)
from tests.unit.pipeline.test_map_point_refresh import random_map, reference_refresh


def shuffled_map(seed: int, n_kf: int = 9, n_points: int = 200) -> InMemoryMapStore:
    """random_map's keyframes, with points whose observations are added in a random keyframe order."""
    rng = np.random.default_rng(seed + 100)
    store = random_map(seed, n_kf=n_kf, n_points=0)
    for _ in range(n_points):
        observers = [
            k
            for k in rng.permutation(n_kf).tolist()[: int(rng.integers(2, n_kf + 1))]
            if np.any(store.get_keyframe(k).point_ids < 0)
        ]
        if len(observers) < 2:
            continue
        pid = store.new_point_id()
        ref = int(rng.choice(observers))
        store.add_point(MapPoint(pid, rng.normal(size=3) + np.array([0.0, 0.0, 4.0]), np.zeros(32, np.uint8), ref, ref))
        for k in observers:
            store.add_observation(pid, k, int(rng.choice(np.flatnonzero(store.get_keyframe(k).point_ids < 0))))
    return store


@pytest.mark.parametrize("seed", [0, 1])
def test_flat_and_sorted_observations_are_the_per_point_loops(seed: int) -> None:
    store = shuffled_map(seed)
    points = store.get_points(store.point_ids())
    counts, kf, feat = flat_observations(points)
    assert counts.tolist() == [len(p.observations) for p in points]
    assert list(zip(kf.tolist(), feat.tolist(), strict=True)) == [o for p in points for o in p.observations.items()]
    assert any(list(p.observations) != sorted(p.observations) for p in points)  # the sort has work to do
    keep = kf % 3 != 0
    point, kf_s, feat_s = sorted_observations(counts, kf, feat, keep)
    expected = [(q, k, f) for q, p in enumerate(points) for k, f in sorted(p.observations.items()) if k % 3 != 0]
    assert list(zip(point.tolist(), kf_s.tolist(), feat_s.tolist(), strict=True)) == expected
    empty = flat_observations([])
    assert [a.size for a in empty] == [0, 0, 0]
    # the in-memory store's own gather (keyframe culling's table): the same arrays from its dictionaries
    some = np.array(store.point_ids()[1::2], np.int64)
    own = store.flat_observations(some)
    expected_some = flat_observations(store.get_points(some.tolist()))
    assert [a.tolist() for a in own] == [a.tolist() for a in expected_some]
    assert [a.size for a in store.flat_observations(np.zeros(0, np.int64))] == [0, 0, 0]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_snapshot_rows_are_the_per_point_loop(seed: int) -> None:
    store = shuffled_map(seed)
    kf_ids = store.keyframe_ids()
    free, fixed = kf_ids[3:], kf_ids[1:3]  # keyframe kf_ids[0] is in neither: its observations are left out
    pids = store.point_ids()[::2]
    snap = snapshot_bundle(store, free, fixed, pids)
    rows = {k: i for i, k in enumerate(free + fixed)}
    expected = [
        (j, rows[k], k, f)
        for j, pid in enumerate(pids)
        for k, f in sorted(store.get_point(pid).observations.items())
        if k in rows
    ]
    prob = snap.problem
    # every point here is in front of some camera (z ~ 4 m), so none is dropped and point rows are pids' order
    assert snap.dropped_point_ids == () and snap.point_ids.tolist() == pids
    got = zip(
        prob.obs_point.tolist(),
        prob.obs_pose.tolist(),
        snap.obs_kf_ids.tolist(),
        snap.obs_feature.tolist(),
        strict=True,
    )
    assert list(got) == expected
    for e, (_, _, k, f) in enumerate(expected):
        feats = store.get_keyframe(k).features
        np.testing.assert_array_equal(prob.uv_px[e], feats.uv_undist_px[f])
        assert prob.level[e] == feats.level[f]
    np.testing.assert_array_equal(prob.T_c_w, np.array([store.get_keyframe(k).T_c_w for k in free + fixed]))


class _ViewsOnlyStore:
    """A store without InMemoryMapStore's own ``flat_observations``: gather_observations reads the points' views."""

    def __init__(self, store: InMemoryMapStore) -> None:
        self._store = store

    def get_points(self, point_ids: list[int]) -> list[MapPoint]:
        return self._store.get_points(point_ids)


@pytest.mark.parametrize("seed", [0, 1])
def test_local_ba_gather_is_the_points_gather(seed: int) -> None:
    """Local BA's gather (the sorted local point ids by unique_point_ids, their observations by gather_observations,
    the snapshot given only ``flat``) builds the problem of the former path (np.unique, get_points, flat_observations,
    the snapshot given the points too) array for array, to the bit."""
    store = shuffled_map(seed)
    kf_ids = store.keyframe_ids()
    local = kf_ids[2:]
    free = local[1:]
    seen = np.unique(np.concatenate([store.get_keyframe(k).point_ids for k in local]))
    pids_old = seen[seen >= 0].tolist()
    points = store.get_points(pids_old)
    flat_old = flat_observations(points)
    pids_new = unique_point_ids([store.get_keyframe(k).point_ids for k in local])
    flat_new = gather_observations(store, pids_new)
    assert pids_new.dtype == np.int64 and pids_new.tolist() == pids_old
    assert [a.tolist() for a in flat_new] == [a.tolist() for a in flat_old]
    assert [a.tolist() for a in gather_observations(_ViewsOnlyStore(store), pids_new)] == [a.tolist() for a in flat_old]  # type: ignore[arg-type]
    observers_old = np.unique(flat_old[1])
    observers_new = unique_point_ids([flat_new[1]])
    assert observers_new.tolist() == observers_old.tolist()
    fixed = np.setdiff1d(observers_new, np.array(free, np.int64)).tolist()
    assert fixed  # keyframes outside the window observe some local points: fixed ones
    old = snapshot_bundle(store, free, fixed, pids_old, points=points, flat=flat_old)
    new = snapshot_bundle(store, free, fixed, pids_new, flat=flat_new)
    for name in ("kf_ids", "point_ids", "obs_kf_ids", "obs_feature"):
        np.testing.assert_array_equal(getattr(new, name), getattr(old, name))
    assert new.dropped_point_ids == old.dropped_point_ids
    for field in (
        "T_c_w",
        "pose_fixed",
        "xyz_w",
        "obs_pose",
        "obs_point",
        "uv_px",
        "u_right_px",
        "level",
        "intrinsics",
    ):
        a, b = getattr(new.problem, field), getattr(old.problem, field)
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)


def test_refresh_of_shuffled_observations_follows_the_per_point_rules() -> None:
    store = shuffled_map(3)
    refresh_points(store, store.point_ids())
    for pid in store.point_ids():
        point = store.get_point(pid)
        normal, d_min, d_max, desc = reference_refresh(point, store)
        np.testing.assert_allclose(point.normal_w, normal, atol=1e-12)
        assert (point.d_min_m, point.d_max_m) == (pytest.approx(d_min, rel=1e-12), pytest.approx(d_max, rel=1e-12))
        np.testing.assert_array_equal(point.descriptor, desc)


def test_fusion_leaves_the_points_a_keyframe_observes_and_fuses_the_others() -> None:
    """fuse_points picks the candidates kf does not observe from kf's point_ids (an observation is recorded in both
    directions): a point kf observes is neither re-added nor replaced, even listed twice; a point kf does not observe
    is added at its feature, and a duplicate of an observed point merges into it (ORB-SLAM Fuse)."""
    from slamkit.pipeline.fusion import fuse_points
    from tests.unit.pipeline.test_local_mapping_step import keyframe, scene

    xyz, desc = scene()
    store = InMemoryMapStore()
    kf0, kf1, kf2 = (keyframe(store, x, xyz, desc) for x in (0.0, 0.2, 0.4))
    for kf in (kf0, kf1, kf2):
        store.add_keyframe(kf)
    # points 0..49 seen by kf0 and kf1; kf2 observes 0..29 too; points 50..59 are duplicates of 30..39 seen by kf0 and kf2
    for j in range(50):
        pid = store.new_point_id()
        store.add_point(MapPoint(pid, xyz[j].copy(), desc[j].copy(), kf0.id, kf0.id))
        store.add_observation(pid, kf0.id, j)
        store.add_observation(pid, kf1.id, j)
        if j < 30:
            store.add_observation(pid, kf2.id, j)
    dup: dict[int, int] = {}
    for j in range(30, 40):
        pid = store.new_point_id()
        store.add_point(MapPoint(pid, xyz[j].copy(), desc[j].copy(), kf0.id, kf0.id))
        store.add_observation(pid, kf2.id, j)
        store.add_observation(pid, kf0.id, 100 + j)  # another feature of kf0 (a wrong match tracking made)
        dup[pid] = j
    refresh_points(store, store.point_ids())
    observed_before = {p: dict(store.get_point(p).observations) for p in range(30)}
    candidates = [*range(50), *range(10)]  # kf2 observes 0..29 (some listed twice); 30..49 it does not
    fused = fuse_points(store, kf2, candidates, 3.0, max_distance=50, chi2_gate=5.991)
    for p in range(30):  # observed by kf2: untouched
        assert store.get_point(p).observations == observed_before[p]
    for j in range(40, 50):  # feature j of kf2 was free: a new observation
        assert store.get_point(j).observations[kf2.id] == j
    for pid, j in dup.items():  # feature j of kf2 held a duplicate with fewer observations: it merges into point j
        assert not store.has_point(pid)
        assert store.get_point(j).observations[kf2.id] == j
    assert fused == 20
