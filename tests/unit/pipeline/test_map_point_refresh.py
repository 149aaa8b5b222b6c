"""The batched map-point refresh (normal, depth range, distinctive descriptor) and the vectorised keyframe
culling count agree exactly with straightforward per-point implementations of ORB-SLAM's rules."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from slamkit.features import Features, Observations
from slamkit.geometry.camera import PinholeCamera
from slamkit.map.entities import KeyFrame, MapPoint
from slamkit.map.store import InMemoryMapStore
from slamkit.pipeline import map_points
from slamkit.pipeline.keyframe_culling import ObservationTable
from slamkit.pipeline.map_points import compute_distinctive_descriptor, refresh_points, update_normal_and_depth

CAMERA = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)


def _record(features: Features) -> Observations:
    """The monocular observation record of hand-made features (bearings through CAMERA)."""
    return Observations.monocular(features, CAMERA.unproject_image(features.uv_undist_px.astype(np.float64)))


N_FEATS = 60


def random_map(seed: int, n_kf: int = 8, n_points: int = 150, rgbd: bool = False) -> InMemoryMapStore:
    """Keyframes at random poses with random descriptors/levels; points observed by random keyframe subsets.
    rgbd: RGB-D records (bf 40 m px, close below 3 m; depths 0.5-6 m, a fifth of the keypoints without one)."""
    rng = np.random.default_rng(seed)
    store = InMemoryMapStore()
    for _ in range(n_kf):
        T = np.eye(4)
        a = rng.normal(scale=0.2, size=3)
        c, s = np.cos(a[2]), np.sin(a[2])
        T[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        T[:3, 3] = rng.normal(scale=0.5, size=3)
        uv = rng.uniform(0, 480, (N_FEATS, 2)).astype(np.float32)
        # few distinct descriptors so median ties happen
        desc = rng.integers(0, 256, (4, 32), dtype=np.uint8)[rng.integers(0, 4, N_FEATS)]
        feats = _record(
            Features(
                uv,
                uv,
                rng.integers(0, 8, N_FEATS).astype(np.int32),
                np.zeros(N_FEATS, np.float32),
                np.zeros(N_FEATS, np.float32),
                desc,
                1.2,
                8,
            )
        )
        if rgbd:
            depth = rng.uniform(0.5, 6.0, N_FEATS).astype(np.float32)
            depth[rng.random(N_FEATS) < 0.2] = np.nan
            u_right = (uv[:, 0] - 40.0 / depth).astype(np.float32)
            feats = dataclasses.replace(
                feats, depth_m=depth, u_right_px=u_right, bf=40.0, th_depth_m=3.0, sensor="rgbd"
            )
        kf_id = store.new_keyframe_id()
        store.add_keyframe(KeyFrame(kf_id, kf_id, float(kf_id), T, CAMERA, feats, np.full(N_FEATS, -1, np.int64)))
    for _ in range(n_points):
        pid = store.new_point_id()
        observers = sorted(rng.choice(n_kf, size=int(rng.integers(1, n_kf + 1)), replace=False).tolist())
        free = [k for k in observers if np.any(store.get_keyframe(k).point_ids < 0)]
        if not free:
            continue
        ref = int(rng.choice(free))
        xyz = rng.normal(size=3) + np.array([0.0, 0.0, 4.0])
        store.add_point(MapPoint(pid, xyz, np.zeros(32, np.uint8), ref, ref))
        for k in free:
            kf = store.get_keyframe(k)
            store.add_observation(pid, k, int(rng.choice(np.flatnonzero(kf.point_ids < 0))))
    return store


def reference_refresh(point: MapPoint, store: InMemoryMapStore) -> tuple[np.ndarray, float, float, np.ndarray]:
    """ORB-SLAM's UpdateNormalAndDepth and ComputeDistinctiveDescriptors written point by point."""
    kfs = {k: store.get_keyframe(k) for k in point.observations}
    units = [(point.xyz_w - kfs[k].center_w) / np.linalg.norm(point.xyz_w - kfs[k].center_w) for k in kfs]
    mean = np.mean(units, axis=0)
    normal = mean / np.linalg.norm(mean)
    ref = kfs[point.ref_kf_id]
    level = int(ref.features.level[point.observations[point.ref_kf_id]])
    d_max = float(np.linalg.norm(point.xyz_w - ref.center_w)) * 1.2**level
    d_min = d_max / 1.2**7
    descs = np.stack([kfs[k].features.descriptors[point.observations[k]] for k in sorted(kfs)])
    bits = np.unpackbits(descs[:, None, :] ^ descs[None, :, :], axis=2).sum(axis=2)
    median = np.median(bits, axis=1)
    return normal, d_min, d_max, descs[int(np.argmin(median))]


@pytest.mark.parametrize(("seed", "n_kf"), [(0, 8), (1, 8), (2, 8), (3, 40)])
def test_batched_refresh_matches_the_per_point_rules(seed: int, n_kf: int) -> None:
    """n_kf 40: points with up to 40 observations (the kernel sorts rows longer than 24 another way)."""
    store = random_map(seed, n_kf=n_kf)
    pids = store.point_ids()
    refresh_points(store, [*pids, *pids[:5], 10_000])  # duplicates and unknown ids are ignored
    for pid in pids:
        point = store.get_point(pid)
        normal, d_min, d_max, desc = reference_refresh(point, store)
        np.testing.assert_allclose(point.normal_w, normal, atol=1e-12)
        assert point.d_max_m == pytest.approx(d_max, rel=1e-12)
        assert point.d_min_m == pytest.approx(d_min, rel=1e-12)
        np.testing.assert_array_equal(point.descriptor, desc)


@pytest.mark.parametrize(("seed", "n_kf"), [(0, 8), (1, 8), (3, 40)])
def test_few_point_descriptor_refresh_matches_the_sorted_gather(
    seed: int, n_kf: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The descriptors-only refresh of a few points (walked point by point, fusion's survivors) writes the very
    descriptors of the sorted batch gather and of ORB-SLAM's per-point rule; the normals and depth ranges stay."""
    few, batch = random_map(seed, n_kf=n_kf), random_map(seed, n_kf=n_kf)
    pids = few.point_ids()
    chunks = [pids[i : i + 7] for i in range(0, len(pids), 7)]
    before = {pid: (few.get_point(pid).normal_w.copy(), few.get_point(pid).d_max_m) for pid in pids}
    calls = {"few": 0}
    gathered = map_points._FewGathered

    def counted(*args: object) -> map_points._FewGathered:
        calls["few"] += 1
        return gathered(*args)  # type: ignore[arg-type]

    monkeypatch.setattr(map_points, "_FewGathered", counted)
    for chunk in chunks:
        refresh_points(few, [*chunk, chunk[0], 10_000], normals=False)
    assert calls["few"] == len(chunks)
    monkeypatch.setattr(map_points, "FEW_POINTS", 0)  # every set through _Gathered
    for chunk in chunks:
        refresh_points(batch, chunk, normals=False)
    assert calls["few"] == len(chunks)
    for pid in pids:
        point = few.get_point(pid)
        np.testing.assert_array_equal(point.descriptor, batch.get_point(pid).descriptor)
        np.testing.assert_array_equal(point.descriptor, reference_refresh(point, few)[3])
        np.testing.assert_array_equal(point.normal_w, before[pid][0])
        assert point.d_max_m == before[pid][1]


def test_single_point_forms_match_the_batch() -> None:
    store = random_map(3)
    batch = random_map(3)
    refresh_points(batch, batch.point_ids())
    for pid in store.point_ids():
        point = store.get_point(pid)
        kfs = {k: store.get_keyframe(k) for k in point.observations}
        update_normal_and_depth(store, point, kfs)
        compute_distinctive_descriptor(store, point, kfs)
        other = batch.get_point(pid)
        np.testing.assert_array_equal(point.normal_w, other.normal_w)
        assert (point.d_min_m, point.d_max_m) == (other.d_min_m, other.d_max_m)
        np.testing.assert_array_equal(point.descriptor, other.descriptor)


def test_descriptor_tie_goes_to_the_lowest_keyframe_id() -> None:
    store = random_map(4, n_kf=3, n_points=0)
    pid = store.new_point_id()
    store.add_point(MapPoint(pid, np.array([0.0, 0.0, 5.0]), np.zeros(32, np.uint8), 1, 1))  # reference: 1
    # two keyframes' descriptors: each has median distance to the pair equal -> first (keyframe 1) wins
    for k in (2, 1):
        kf = store.get_keyframe(k)
        kf.features.descriptors[0] = np.full(32, k, np.uint8)
        store.add_observation(pid, k, 0)
    refresh_points(store, [pid])
    np.testing.assert_array_equal(store.get_point(pid).descriptor, np.full(32, 1, np.uint8))


def test_observers_missing_from_the_mapping_are_ignored() -> None:
    store = random_map(5)
    point = next(store.get_point(p) for p in store.point_ids() if len(store.get_point(p).observations) >= 3)
    before = point.d_max_m
    others = {k: store.get_keyframe(k) for k in point.observations if k != point.ref_kf_id}
    update_normal_and_depth(store, point, others)  # no reference keyframe: the depth range stays
    assert point.d_max_m == before
    units = [(point.xyz_w - kf.center_w) / np.linalg.norm(point.xyz_w - kf.center_w) for kf in others.values()]
    mean = np.mean(units, axis=0)
    np.testing.assert_allclose(point.normal_w, mean / np.linalg.norm(mean), atol=1e-12)


def naive_redundancy(store: InMemoryMapStore, kf_id: int, m: int) -> tuple[int, int]:
    """ORB-SLAM KeyFrameCulling's count, observation by observation (stereo/RGB-D: close points only)."""
    k = store.get_keyframe(kf_id)
    n_points = redundant = 0
    for feat in np.flatnonzero(k.point_ids >= 0):
        if k.features.bf > 0.0 and not (0.0 <= k.features.depth_m[feat] <= k.features.th_depth_m):
            continue  # ORB-SLAM2: if(!mbMonocular) skip mvDepth[i] > mThDepth || mvDepth[i] < 0 (NaN: -1)
        point = store.get_point(int(k.point_ids[feat]))
        n_points += 1
        if len(point.observations) <= m:
            continue
        level = int(k.features.level[feat])
        n_obs = sum(
            1
            for o, f in point.observations.items()
            if o != kf_id and int(store.get_keyframe(o).features.level[f]) <= level + 1
        )
        redundant += n_obs >= m
    return n_points, redundant


@pytest.mark.parametrize("seed,rgbd", [(0, False), (1, False), (2, True)])
def test_culling_count_matches_the_per_observation_loop_while_culling(seed: int, rgbd: bool) -> None:
    store = random_map(seed, n_kf=10, n_points=300, rgbd=rgbd)
    candidates = store.keyframe_ids()[1:]
    table = ObservationTable(store, candidates)  # asked one keyframe at a time
    batch = ObservationTable(store, candidates)  # asked for every candidate left at once, as local mapping does
    redundant_seen = erased_seen = 0
    for i, k in enumerate(candidates):
        n_points, redundant = batch.redundancies(candidates, 3, i)
        expected = [naive_redundancy(store, r, 3) for r in candidates[i:]]
        assert list(zip(n_points[i:].tolist(), redundant[i:].tolist(), strict=True)) == expected
        assert table.redundancy(k, 3) == expected[0]
        redundant_seen += expected[0][1]
        if k % 3 == 0:  # erase some keyframes on the way: later counts must see their observations gone
            # and, as keyframe culling, the points the keyframe leaves with two observations or fewer
            seen = store.get_keyframe(k).point_ids
            seen = seen[seen >= 0].copy()
            store.remove_keyframe(k)
            seen = seen[store.has_points(seen)]
            erased = seen[store.point_rows(seen, "n_observations") <= 2]
            for pid in erased.tolist():
                store.remove_point(pid)
            erased_seen += erased.size
            table.cull(k, erased)
            batch.cull(k, erased)
    assert redundant_seen > 0 and erased_seen > 0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_descriptor_choice_skipping_rows_equals_the_full_median_argmin(seed: int) -> None:
    """The kernel skips a row whose median cannot beat the best so far (a count, no sort): its choice stays
    np.argmin of every row's np.median (first on ties), for clustered descriptors (a point's real observations: near
    copies plus outliers, many equal medians) and uniform ones, 2 to 60 observations (both sorts, n <= 24 and > 24)."""
    rng = np.random.default_rng(seed)
    sizes = rng.integers(2, 61, 400)
    rows: list[np.ndarray] = []
    for q, n in enumerate(sizes.tolist()):
        if q % 3 == 2:
            rows.append(rng.integers(0, 256, (n, 32), dtype=np.uint8))
            continue
        base = rng.integers(0, 256, 32, dtype=np.uint8)
        flips = rng.random((n, 256)) < rng.choice([0.0, 0.02, 0.1])
        near = np.packbits(np.unpackbits(base)[None, :] ^ flips, axis=1)
        outlier = rng.random(n) < 0.2
        near[outlier] = rng.integers(0, 256, (int(outlier.sum()), 32), dtype=np.uint8)
        rows.append(near)
    ptr = np.zeros(sizes.size + 1, np.int64)
    np.cumsum(sizes, out=ptr[1:])
    desc = np.ascontiguousarray(np.concatenate(rows))
    P, E = sizes.size, int(ptr[-1])
    *_, best = map_points._refresh_kernel(
        np.zeros((P, 3)),
        ptr,
        np.zeros((E, 3)),
        desc.view(np.uint64),
        np.full(P, -1, np.int64),
        np.zeros(E, np.int64),
        np.ones(P),
        np.ones(P, np.int64),
        False,
        True,
    )
    for q in range(P):
        d = rows[q]
        bits = np.unpackbits(d[:, None, :] ^ d[None, :, :], axis=2).sum(axis=2)
        assert best[q] == ptr[q] + int(np.argmin(np.median(bits, axis=1)))
