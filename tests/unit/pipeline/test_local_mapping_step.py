"""Local mapping on a small exact map: triangulation recovers the true points, the local BA runs on a snapshot
without the map's write lock (a reader gets in while the optimizer works), and the Cholesky kernel the faster
path relies on is exact."""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
import pytest
from slamkit_scipy.kernels import cholesky_solve_upper

from slamkit.features import Features, Observations
from slamkit.geometry.camera import PinholeCamera
from slamkit.interfaces import AbortToken, BowDescription, PlaceRecognizer
from slamkit.map.atlas import Atlas
from slamkit.map.entities import KeyFrame, MapPoint
from slamkit.map.store import InMemoryMapStore
from slamkit.pipeline.config import LocalMappingConfig
from slamkit.pipeline.keyframe_insertion import insert_keyframe
from slamkit.pipeline.keyframe_pins import KeyFramePins
from slamkit.pipeline.local_mapping import LocalMapper, _free_pairs
from slamkit.pipeline.map_points import add_observations, add_points, new_pair_points, refresh_points
from slamkit.pipeline.matching import close_pairs
from slamkit.plugins import ComponentRegistry
from slamkit.problems import BundleProblem, BundleResult

CAMERA = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)


def _record(features: Features) -> Observations:
    """The monocular observation record of hand-made features (bearings through CAMERA)."""
    return Observations.monocular(features, CAMERA.unproject_image(features.uv_undist_px.astype(np.float64)))


N_POINTS = 400
N_MAPPED = 200  # points 0..199 are in the map; 200..399 are for local mapping to triangulate


def scene(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    xyz = rng.uniform([-1.5, -1.0, 4.0], [1.5, 1.0, 6.0], (N_POINTS, 3))
    desc = rng.integers(0, 256, (N_POINTS, 32), dtype=np.uint8)
    return xyz, desc


def keyframe(
    store: InMemoryMapStore, x_m: float, xyz: np.ndarray, desc: np.ndarray, point_ids: np.ndarray | None = None
) -> KeyFrame:
    """A camera at (x_m, 0, 0) looking along +z; feature j is the exact projection of point j. point_ids: the
    points tracking matched (default none)."""
    T = np.eye(4)
    T[0, 3] = -x_m
    cam = xyz @ T[:3, :3].T + T[:3, 3]
    uv = (cam[:, :2] / cam[:, 2:] * 500.0 + [320.0, 240.0]).astype(np.float32)
    feats = _record(
        Features(
            uv,
            uv,
            np.zeros(N_POINTS, np.int32),
            np.zeros(N_POINTS, np.float32),
            np.ones(N_POINTS, np.float32),
            desc.copy(),
            1.2,
            8,
        )
    )
    kf_id = store.new_keyframe_id()
    matched = np.full(N_POINTS, -1, np.int64) if point_ids is None else point_ids
    return KeyFrame(kf_id, kf_id, float(kf_id), T, CAMERA, feats, matched)


class WatchingOptimizer:
    """The scipy optimizer, checking from another thread that the map can be read while BA runs."""

    def __init__(self, store: InMemoryMapStore) -> None:
        registry = ComponentRegistry.discover()
        self.inner = registry.instantiate("optimizer", {"_target_": registry.get("optimizer", "scipy").spec.target})
        self.store = store
        self.reader_got_in: list[bool] = []

    def bundle_adjust(self, problem: BundleProblem, abort: AbortToken | None = None) -> BundleResult:
        got_in = threading.Event()

        def read() -> None:
            with self.store.read():
                got_in.set()

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        reader.join(timeout=10.0)
        self.reader_got_in.append(got_in.is_set())
        return self.inner.bundle_adjust(problem, abort)

    def __getattr__(self, name: str) -> object:
        return getattr(self.inner, name)


class WordsOnlyRecognizer:
    """A place recognizer with no vocabulary structure to restrict matching: its bags of words carry no direct
    index, and ``candidate_pairs`` returns every close pair, as the PlaceRecognizer protocol allows (words and the
    keyframe database are DBoW's)."""

    def __init__(self, inner: PlaceRecognizer) -> None:
        self.inner = inner

    def transform(self, descriptors: np.ndarray) -> BowDescription:
        return BowDescription(self.inner.transform(descriptors).words)

    def candidate_pairs(
        self,
        feats1: Features,
        bow1: BowDescription,
        feats2: Features,
        bow2: BowDescription,
        mask1: np.ndarray | None = None,
        mask2: np.ndarray | None = None,
        *,
        max_distance: int,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        m1 = np.ones(len(feats1), bool) if mask1 is None else mask1
        m2 = np.ones(len(feats2), bool) if mask2 is None else mask2
        return close_pairs(feats1.descriptors, feats2.descriptors, m1, m2, max_distance)

    def __getattr__(self, name: str) -> object:
        return getattr(self.inner, name)


def place_recognizer(name: str | None) -> PlaceRecognizer | None:
    if name is None:
        return None
    registry = ComponentRegistry.discover()
    dbow: PlaceRecognizer = registry.instantiate("place", registry.get("place", "dbow").config_node())
    return dbow if name == "dbow" else WordsOnlyRecognizer(dbow)  # type: ignore[return-value]


def two_keyframe_map(place: PlaceRecognizer | None) -> tuple[InMemoryMapStore, np.ndarray, np.ndarray, np.ndarray]:
    """A map of keyframes 0 and 1 (0.3 m apart) sharing the scene's first N_MAPPED points, their bags of words from
    ``place`` (None: none); returns (store, the scene's points (N, 3) m, descriptors (N, 32), the (N,) point ids a
    third keyframe tracked: the mapped ones, -1 elsewhere)."""
    xyz, desc = scene()
    store = InMemoryMapStore()
    kf0, kf1 = keyframe(store, 0.0, xyz, desc), keyframe(store, 0.3, xyz, desc)
    for kf in (kf0, kf1):
        store.add_keyframe(kf)
        if place is not None:
            store.set_keyframe_bow(kf.id, place.transform(kf.features.descriptors))
    for j in range(N_MAPPED):
        pid = store.new_point_id()
        store.add_point(MapPoint(pid, xyz[j].copy(), desc[j].copy(), 0, 0))
        store.add_observation(pid, 0, j)
        store.add_observation(pid, 1, j)
    refresh_points(store, store.point_ids())
    store.update_connections(0)
    store.update_connections(1)
    tracked = np.full(N_POINTS, -1, np.int64)
    tracked[:N_MAPPED] = np.arange(N_MAPPED)  # matched by tracking
    return store, xyz, desc, tracked


@pytest.mark.parametrize("place_name", [None, "dbow", "words-only"])
def test_step_triangulates_true_points_and_runs_ba_without_the_write_lock(place_name: str | None) -> None:
    """Without a place recognizer every pair of free features is a triangulation candidate; with one, the candidates
    come from its ``candidate_pairs`` (DBoW: same vocabulary node; a recognizer without a direct index: every
    pair), and local mapping reads nothing else of the bags of words."""
    place = place_recognizer(place_name)
    store, xyz, desc, tracked = two_keyframe_map(place)
    kf2 = keyframe(store, 0.6, xyz, desc, tracked)
    optimizer = WatchingOptimizer(store)
    mapper = LocalMapper(LocalMappingConfig(), Atlas.of(store), optimizer, place)  # type: ignore[arg-type]
    out = mapper.step(kf2)
    assert optimizer.reader_got_in == [True]
    assert out.points_created >= 0.9 * (N_POINTS - N_MAPPED)
    # every new point sits on the true point of its feature (exact projections, rounded to float32 pixels)
    new = [store.get_point(p) for p in store.point_ids() if p >= N_MAPPED]
    assert len(new) == out.points_created
    for point in new:
        feat = point.observations[kf2.id]
        assert set(point.observations.values()) == {feat}
        np.testing.assert_allclose(point.xyz_w, xyz[feat], atol=1e-4)  # float32 pixels
        np.testing.assert_array_equal(point.descriptor, desc[feat])
        # level-0 features of the reference keyframe (kf2): d_max is its distance, d_min that / 1.2^7
        assert point.ref_kf_id == kf2.id
        assert point.d_max_m == pytest.approx(np.linalg.norm(point.xyz_w - kf2.center_w), rel=1e-6)
        assert point.d_min_m == pytest.approx(point.d_max_m / 1.2**7, rel=1e-12)
    assert set(store.covisibility.neighbors(kf2.id)) == {0, 1}
    # exact data: BA keeps the poses where they are and flags nothing
    assert out.ba_outliers == 0
    np.testing.assert_allclose(store.get_keyframe(kf2.id).T_c_w[0, 3], -0.6, atol=1e-5)
    assert out.ba_due and not out.ba_skipped and not out.ba_aborted  # the third keyframe is due a local BA: it ran


def test_a_local_ba_a_newer_keyframe_aborted_before_it_started_is_skipped_and_reported() -> None:
    """ORB-SLAM's mbAbortBA set before the local BA: no BA runs (the optimizer is never called), the outcome says the
    keyframe was due one and skipped it, and the run's metrics count it out of the completed ones."""
    from slamkit.eval.run_metrics import local_ba_completed

    store, xyz, desc, tracked = two_keyframe_map(None)
    optimizer = WatchingOptimizer(store)
    mapper = LocalMapper(LocalMappingConfig(), Atlas.of(store), optimizer, None)  # type: ignore[arg-type]
    abort = threading.Event()
    abort.set()
    skipped = mapper.step(keyframe(store, 0.6, xyz, desc, tracked), abort)
    assert optimizer.reader_got_in == []  # bundle_adjust was never called
    assert skipped.ba_due and skipped.ba_skipped and not skipped.ba_aborted
    ran = mapper.step(keyframe(store, 0.9, xyz, desc, tracked))
    assert optimizer.reader_got_in == [True]
    assert ran.ba_due and not ran.ba_skipped and not ran.ba_aborted
    counts = local_ba_completed([skipped, ran])
    assert counts == {"due": 2, "completed": 1, "skipped": 1, "aborted": 0, "fraction": 0.5}


@pytest.mark.parametrize("n", [1, 6, 150, 200])
def test_cholesky_kernel_reads_the_upper_triangle_only(n: int) -> None:
    rng = np.random.default_rng(n)
    A = rng.normal(size=(n, n))
    S = A @ A.T + n * np.eye(n)
    if n >= 150:  # block-banded, as the reduced camera system of a forward-moving camera
        band = np.abs(np.subtract.outer(np.arange(n) // 6, np.arange(n) // 6)) > 3
        S[band] = 0.0
        S += n * np.eye(n)
    b = rng.normal(size=n)
    garbage = S.copy()
    garbage[np.tril_indices(n, -1)] = 1e300  # never read
    np.testing.assert_allclose(cholesky_solve_upper(garbage, b), np.linalg.solve(S, b), rtol=1e-9, atol=1e-12)


def test_cholesky_kernel_signals_an_indefinite_system_with_nan() -> None:
    S = np.array([[1.0, 2.0], [2.0, 1.0]])  # eigenvalues 3 and -1
    assert np.all(np.isnan(cholesky_solve_upper(S, np.ones(2))))
    assert np.all(np.isnan(cholesky_solve_upper(np.array([[np.nan]]), np.ones(1))))


def keyframes_seeing_the_same_points(n: int, spacing_m: float) -> tuple[InMemoryMapStore, list[KeyFrame]]:
    """``n`` keyframes ``spacing_m`` apart along x, each observing all N_MAPPED points of ``scene()``, connected."""
    xyz, desc = scene()
    store = InMemoryMapStore()
    kfs = [keyframe(store, spacing_m * i, xyz, desc) for i in range(n)]
    for kf in kfs:
        store.add_keyframe(kf)
    for j in range(N_MAPPED):
        pid = store.new_point_id()
        store.add_point(MapPoint(pid, xyz[j].copy(), desc[j].copy(), 0, 0))
        for kf in kfs:
            store.add_observation(pid, kf.id, j)
    refresh_points(store, store.point_ids())
    for kf in kfs:
        store.update_connections(kf.id)
    return store, kfs


@pytest.mark.parametrize("pinned", [(), (2,)])
def test_keyframe_culling_leaves_the_keyframes_loop_closing_pinned(pinned: tuple[int, ...]) -> None:
    """Five keyframes 5 cm apart see the same 200 points: culling (VI-E) at the last erases the redundant ones in
    order (1 and 2; then 3 is seen by too few others), but never one loop closing pinned (ORB-SLAM SetNotErase)."""
    store, kfs = keyframes_seeing_the_same_points(5, 0.05)
    pins = KeyFramePins()
    pins.pin(*pinned)
    mapper = LocalMapper(LocalMappingConfig(), Atlas.of(store), None, pins=pins)  # type: ignore[arg-type]
    with store.write():
        culled = {c.kf_id for c in mapper._cull_keyframes(kfs[4])}
    assert culled == ({1, 3} if pinned else {1, 2})
    assert all(store.has_keyframe(k) for k in pinned)


@pytest.mark.parametrize(
    ("aborted", "max_candidates", "expected"),
    [(False, 101, set(range(1, 28))), (True, 101, set(range(1, 21))), (False, 10, set(range(1, 10)))],
)
def test_keyframe_culling_visits_as_many_covisible_keyframes_as_orbslam3(
    aborted: bool, max_candidates: int, expected: set[int]
) -> None:
    """Thirty keyframes 1 cm apart see the same 200 points, so each is redundant while three others remain. Culling
    at the last visits its covisible keyframes best first (ties: lower id first; the origin 0 is visited, never
    culled): every one up to 27 (then 28 has two others left) with ORB-SLAM3's limit of 101; only the first 21
    visited once the local BA was told to stop (ORB-SLAM3 `count > 20 && mbAbortBA`: keyframes 1-20); the first
    ``max_candidates`` with a smaller limit."""
    store, kfs = keyframes_seeing_the_same_points(30, 0.01)
    abort = threading.Event()
    if aborted:
        abort.set()
    cfg = LocalMappingConfig(keyframe_culling_max_candidates=max_candidates)
    mapper = LocalMapper(cfg, Atlas.of(store), None)  # type: ignore[arg-type]
    with store.write():
        culled = {c.kf_id for c in mapper._cull_keyframes(kfs[-1], abort)}
    assert culled == expected
    assert all(store.has_keyframe(k) != (k in expected) for k in range(30))


def test_the_one_keyframe_inserter_turns_tracked_matches_into_observations_once() -> None:
    """slamkit/pipeline/keyframe_insertion.py: a keyframe tracking made enters the map with its tracked points as
    observations (their viewing data refreshed); inserting a keyframe the map holds (the two of a new map, which
    local mapping processes after initialisation inserted them) changes nothing."""
    xyz, desc = scene()
    store = InMemoryMapStore()
    kf0 = keyframe(store, 0.0, xyz, desc)
    assert insert_keyframe(store, kf0)
    for j in range(N_MAPPED):
        pid = store.new_point_id()
        store.add_point(MapPoint(pid, xyz[j].copy(), desc[j].copy(), kf0.id, kf0.id))
        store.add_observation(pid, kf0.id, j)
    refresh_points(store, store.point_ids())
    tracked = np.full(N_POINTS, -1, np.int64)
    tracked[:N_MAPPED] = np.arange(N_MAPPED)
    kf1 = keyframe(store, 0.3, xyz, desc, tracked)
    before = store.get_point(0).normal_w.copy()
    assert insert_keyframe(store, kf1)
    assert all(store.get_point(p).observations == {kf0.id: p, kf1.id: p} for p in range(N_MAPPED))
    assert not np.allclose(store.get_point(0).normal_w, before), "normals refreshed with the new view"
    assert not insert_keyframe(store, kf1) and not insert_keyframe(store, kf0)
    assert store.n_keyframes() == 2 and store.get_point(0).observations == {kf0.id: 0, kf1.id: 0}


@pytest.mark.parametrize("bad_max", [2, 0])
def test_points_a_culled_keyframe_leaves_with_two_observations_are_erased(bad_max: int) -> None:
    """ORB-SLAM2 KeyFrame::SetBadFlag -> MapPoint::EraseObservation: nObs <= 2 -> SetBadFlag. Five keyframes see
    100 points; keyframes 1-3 also see 5 more. Culling at keyframe 4 erases 1 and 2 (95% / 100% redundant): the 5
    points are left with fewer than three observers and go (``point_bad_max_observations`` 2); with 0 they stay."""
    xyz, desc = scene()
    store = InMemoryMapStore()
    kfs = [keyframe(store, 0.05 * i, xyz, desc) for i in range(5)]
    for kf in kfs:
        store.add_keyframe(kf)
    pids = []
    for j in range(105):
        pid = store.new_point_id()
        pids.append(pid)
        store.add_point(MapPoint(pid, xyz[j].copy(), desc[j].copy(), 0, 0))
        for kf in kfs if j < 100 else kfs[1:4]:
            store.add_observation(pid, kf.id, j)
    refresh_points(store, store.point_ids())
    for kf in kfs:
        store.update_connections(kf.id)
    cfg = LocalMappingConfig(point_bad_max_observations=bad_max)
    mapper = LocalMapper(cfg, Atlas.of(store), None)  # type: ignore[arg-type]
    with store.write():
        culled = {c.kf_id for c in mapper._cull_keyframes(kfs[4])}
    assert culled == {1, 2}
    assert all(store.has_point(p) for p in pids[:100])
    assert all(store.has_point(p) != (bad_max == 2) for p in pids[100:])


def test_local_ba_refreshes_the_viewing_data_of_the_points_it_moves() -> None:
    """ORB-SLAM2/3 LocalBundleAdjustment ends with SetWorldPos + UpdateNormalAndDepth for every local point: a point
    triangulated 30 cm too deep is pulled back onto its exact projections by the BA, and its distance range
    [d_min, d_max] (which tracking's scale prediction and range check read) is that of the optimised point, not of
    the one it replaced."""
    xyz, desc = scene()
    store = InMemoryMapStore()
    kfs = [keyframe(store, 0.3 * i, xyz, desc) for i in range(3)]
    for kf in kfs:
        store.add_keyframe(kf)
    for j in range(N_MAPPED):
        pid = store.new_point_id()
        store.add_point(MapPoint(pid, xyz[j].copy(), desc[j].copy(), 0, 0))
        for kf in kfs:
            store.add_observation(pid, kf.id, j)
    wrong = xyz[7] + np.array([0.0, 0.0, 0.3])
    store.assign_points(np.array([7]), "xyz_w", wrong[None])
    refresh_points(store, store.point_ids())
    for kf in kfs:
        store.update_connections(kf.id)
    stale_d_max = store.get_point(7).d_max_m
    cfg = LocalMappingConfig(ba_update_normal_and_depth=True)
    mapper = LocalMapper(cfg, Atlas.of(store), WatchingOptimizer(store))  # type: ignore[arg-type]
    outliers, aborted = mapper._local_bundle_adjustment(kfs[2], None)
    assert not aborted and outliers == 0
    point = store.get_point(7)
    np.testing.assert_allclose(point.xyz_w, xyz[7], atol=5e-3)  # 30 cm off before
    ref_center = store.get_keyframe(point.ref_kf_id).center_w
    assert point.d_max_m == pytest.approx(np.linalg.norm(point.xyz_w - ref_center), rel=1e-9)
    assert abs(point.d_max_m - stale_d_max) > 0.1


@pytest.mark.parametrize("culled", [True, False])
def test_points_of_a_new_map_face_recent_point_culling(culled: bool) -> None:
    """ORB-SLAM LocalMapping::ProcessNewKeyFrame: a point the processed keyframe already observes (every point of the
    monocular initial map, created with both keyframes' observations and pKFcur as first keyframe) joins the recent
    points, so MapPointCulling (VI-B) erases those found in fewer than 25% of the frames predicting them, and those
    still seen by two keyframes once two keyframes have passed the first one. Without ``new_map_points_culled``
    they all stay."""
    xyz, desc = scene()
    store = InMemoryMapStore()
    kf0, kf1 = keyframe(store, 0.0, xyz, desc), keyframe(store, 0.3, xyz, desc)
    for kf in (kf0, kf1):
        store.add_keyframe(kf)
    for j in range(N_MAPPED):
        pid = store.new_point_id()
        store.add_point(MapPoint(pid, xyz[j].copy(), desc[j].copy(), kf0.id, kf1.id))
        store.add_observation(pid, kf0.id, j)
        store.add_observation(pid, kf1.id, j)
    refresh_points(store, store.point_ids())
    store.update_connections(kf0.id)
    store.update_connections(kf1.id)
    mapper = LocalMapper(LocalMappingConfig(new_map_points_culled=culled), Atlas.of(store), None)  # type: ignore[arg-type]
    with store.write():
        for kf in (kf0, kf1):  # as initialisation hands them over: already in the map, their points observed
            mapper._process_new_keyframe(kf)
            assert mapper._cull_recent_points(kf) == 0
    store.increase_visible(np.arange(50), 10)  # points 0-49: predicted in 10 more frames, found in none
    tracked = np.full(N_POINTS, -1, np.int64)
    tracked[100:N_MAPPED] = np.arange(100, N_MAPPED)  # later keyframes see points 100-199 only
    kf2 = keyframe(store, 0.6, xyz, desc, tracked)
    with store.write():
        mapper._process_new_keyframe(kf2)
        found_ratio_culled = mapper._cull_recent_points(kf2)  # kf2 is one keyframe past the first (kf1)
    kf3 = keyframe(store, 0.9, xyz, desc, tracked.copy())
    with store.write():
        mapper._process_new_keyframe(kf3)
        observation_culled = mapper._cull_recent_points(kf3)  # two past: two observations are too few
    alive = store.has_points(np.arange(N_MAPPED))
    if culled:
        assert (found_ratio_culled, observation_culled) == (50, 50)
        assert not alive[:100].any() and alive[100:].all()
    else:
        assert (found_ratio_culled, observation_culled) == (0, 0)
        assert alive.all()


def _one_neighbour_at_a_time(mapper: LocalMapper, kf: KeyFrame) -> int:
    """The triangulation of VI-C as ORB-SLAM writes it: each neighbour's new points added to the map before the next
    neighbour is matched (the reference for the planned, written-at-once ``_create_new_points``)."""
    store = mapper.store
    created = 0
    for n_id in store.covisibility.best_neighbors(kf.id, mapper.cfg.triangulation_neighbors):
        found = mapper._triangulate_with(kf, n_id)
        if found is None:
            continue
        kf2 = store.get_keyframe(n_id)
        i1, i2, xyz = found
        sel = _free_pairs(kf, kf2, i1, i2)
        ids = np.array([store.new_point_id() for _ in range(sel.size)], np.int64)
        add_points(store, new_pair_points(ids, xyz[sel], kf, i1[sel], kf2, i2[sel]))
        add_observations(store, ids, kf.id, i1[sel])
        add_observations(store, ids, n_id, i2[sel])
        created += sel.size
    return created


def _map_of(store: InMemoryMapStore) -> list[tuple[object, ...]]:
    """Every point's id, position, descriptor, reference keyframe, normal, depth range and observations (in order)."""
    return [
        (
            p.id,
            p.xyz_w.tobytes(),
            p.descriptor.tobytes(),
            p.ref_kf_id,
            p.normal_w.tobytes(),
            p.d_min_m,
            p.d_max_m,
            list(p.observations.items()),
        )
        for p in store.get_points(store.point_ids())
    ]


@pytest.mark.parametrize("place_name", [None, "dbow"])
def test_new_points_planned_per_neighbour_make_the_map_of_adding_them_one_neighbour_at_a_time(
    place_name: str | None,
) -> None:
    """Four neighbours see the new keyframe's free features (with noise on the pixels, so the neighbours disagree on
    the points): the features the first neighbours take are not offered to the next, and the map the planned
    points leave is, point by point and observation by observation, the one of adding each neighbour's at once."""
    place = place_recognizer(place_name)
    maps = []
    for reference in (False, True):
        xyz, desc = scene(1)
        store = InMemoryMapStore()
        rng = np.random.default_rng(7)
        kfs = []
        for x in (0.0, 0.15, 0.3, 0.45, 0.6):
            kf = keyframe(store, x, xyz, desc)
            f = kf.features
            noisy = f.uv_undist_px + rng.normal(0.0, 0.7, f.uv_undist_px.shape).astype(np.float32)
            levels = rng.integers(0, 3, len(f)).astype(np.int32)
            feats = Features(noisy, noisy, levels, f.angle_deg, f.response, f.descriptors, 1.2, 8)
            kfs.append(dataclasses.replace(kf, features=_record(feats)))
        for kf in kfs[:4]:
            store.add_keyframe(kf)
            if place is not None:
                store.set_keyframe_bow(kf.id, place.transform(kf.features.descriptors))
        for j in range(N_MAPPED):
            pid = store.new_point_id()
            store.add_point(MapPoint(pid, xyz[j].copy(), desc[j].copy(), 0, 0))
            for kf in kfs[:4]:
                store.add_observation(pid, kf.id, j)
        refresh_points(store, store.point_ids())
        tracked = np.full(N_POINTS, -1, np.int64)
        tracked[:N_MAPPED] = np.arange(N_MAPPED)
        new = dataclasses.replace(kfs[4], point_ids=tracked)
        store.add_keyframe(new)
        if place is not None:
            store.set_keyframe_bow(new.id, place.transform(new.features.descriptors))
        for kf in store.keyframe_ids():
            store.update_connections(kf)
        mapper = LocalMapper(LocalMappingConfig(), Atlas.of(store), None, place)  # type: ignore[arg-type]
        kf = store.get_keyframe(new.id)
        created = _one_neighbour_at_a_time(mapper, kf) if reference else mapper._create_new_points(kf)
        maps.append((created, _map_of(store), store.get_keyframe(new.id).point_ids.tolist()))
        assert len(store.covisibility.best_neighbors(new.id, 20)) == 4
    assert maps[0] == maps[1]
    created, points, _ = maps[0]
    # the points spread over several neighbours, and no feature of the new keyframe has two
    observers = {tuple(sorted(obs)) for *_, obs in points[N_MAPPED:] for obs in [dict(obs)]}
    assert created > 100 and len(observers) > 1
