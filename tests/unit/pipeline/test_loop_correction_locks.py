"""Loop correction holds the map's write lock only to write: what it computes (the corrected neighbourhood, the
essential-graph problem, the optimized map's poses, positions and normals) runs under the read lock, so tracking
reads the map meanwhile; the corrected map is the one the step-by-step correction (move, set poses, refresh, all
under one write lock) gives, bit for bit."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import numpy as np
import pytest

import slamkit.pipeline.loop_closing as loop_closing
from slamkit.features import Features, Observations
from slamkit.geometry.camera import PinholeCamera
from slamkit.geometry.sim3 import Sim3
from slamkit.geometry.so3 import so3_exp
from slamkit.map.atlas import Atlas
from slamkit.map.entities import KeyFrame, MapPoint
from slamkit.map.store import InMemoryMapStore
from slamkit.pipeline.config import LoopClosingConfig
from slamkit.pipeline.loop_correction import (
    LoopCorrection,
    apply_essential_graph,
    apply_loop_correction,
    essential_graph_problem,
    pose_of_sim3,
    propagate_loop_sim3,
    read_then_write,
)
from slamkit.pipeline.map_points import refresh_points
from slamkit.pipeline.outcomes import LoopOutcome
from slamkit.plugins import ComponentRegistry
from slamkit.problems import EssentialGraphResult

N = 12  # keyframes on a line, each sharing SHARED points with the one before
SHARED = 120
N_FEATS = 2 * SHARED
CAMERA = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)


def _features(rng: np.random.Generator) -> Observations:
    """A keyframe's hand-made features: keypoints spread over the image, levels 0-3, random descriptors."""
    uv = rng.uniform([0, 0], [640, 480], (N_FEATS, 2)).astype(np.float32)
    feats = Features(
        uv,
        uv.copy(),
        rng.integers(0, 4, N_FEATS).astype(np.int32),
        np.zeros(N_FEATS, np.float32),
        np.zeros(N_FEATS, np.float32),
        rng.integers(0, 256, (N_FEATS, 32)).astype(np.uint8),
        1.2,
        8,
    )
    return Observations.monocular(feats, CAMERA.unproject_image(uv.astype(np.float64)))


def line_map(seed: int = 0) -> InMemoryMapStore:
    """N keyframes 0.3 m apart along x, with a little yaw each, and points in front of them (positions, normals and
    depth ranges from the observations), each seen by two consecutive keyframes."""
    rng = np.random.default_rng(seed)
    store = InMemoryMapStore()
    used = [0] * N
    for k in range(N):
        T_c_w = np.eye(4)
        T_c_w[:3, :3] = so3_exp(np.array([0.0, 0.02 * k, 0.0]))
        T_c_w[:3, 3] = -T_c_w[:3, :3] @ np.array([0.3 * k, 0.0, 0.0])
        kf_id = store.new_keyframe_id()
        store.add_keyframe(KeyFrame(kf_id, k, float(k), T_c_w, CAMERA, _features(rng), np.full(N_FEATS, -1, np.int64)))
        if k == 0:
            continue
        for _ in range(SHARED):
            pid = store.new_point_id()
            xyz = np.array([0.3 * k, 0.0, 0.0]) + rng.normal(0.0, 1.0, 3) + np.array([0.0, 0.0, 4.0])
            store.add_point(MapPoint(pid, xyz, np.zeros(32, np.uint8), k - 1, k - 1))
            for o in (k - 1, k):
                store.add_observation(pid, o, used[o])
                used[o] += 1
        store.update_connections(kf_id)
    refresh_points(store, store.point_ids())
    return store


def loop_sim3(store: InMemoryMapStore) -> Sim3:
    """The current (last) keyframe's 'corrected' pose: its pose moved by a small Sim3 (scale 1.02, 1 deg, 5 cm)."""
    T = store.get_keyframe(N - 1).T_c_w
    drift = Sim3(1.02, so3_exp(np.array([0.0, 0.0, np.radians(1.0)])), np.array([0.05, 0.0, 0.0]))
    return drift @ Sim3(1.0, T[:3, :3], T[:3, 3])


def optimized(problem_S_c_w: np.ndarray) -> EssentialGraphResult:
    """An essential-graph result: every pose but the first moved by its own small Sim3."""
    rng = np.random.default_rng(7)
    out = problem_S_c_w.copy()
    for i in range(1, out.shape[0]):
        d = Sim3(1.0 + 0.01 * rng.uniform(), so3_exp(rng.normal(0.0, 0.01, 3)), rng.normal(0.0, 0.02, 3))
        out[i] = d.matrix() @ out[i]
    return EssentialGraphResult(S_c_w=out, cost_initial=1.0, cost_final=0.5, iterations=3)


def snapshot(store: InMemoryMapStore) -> dict[str, np.ndarray]:
    """Every keyframe pose and every point attribute loop correction writes."""
    pids = np.array(store.point_ids(), np.int64)
    out = {a: store.point_rows(pids, a) for a in ("xyz_w", "normal_w", "d_min_m", "d_max_m", "descriptor")}
    out["poses"] = np.stack([store.get_keyframe(k).T_c_w for k in store.keyframe_ids()])
    # what the points themselves hold (the store mirrors them in its table)
    out["point_xyz"] = np.stack([store.get_point(p).xyz_w for p in pids.tolist()])
    out["point_normal"] = np.stack([store.get_point(p).normal_w for p in pids.tolist()])
    out["point_d"] = np.array([[store.get_point(p).d_min_m, store.get_point(p).d_max_m] for p in pids.tolist()])
    return out


def assert_same_bits(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> None:
    assert a.keys() == b.keys()
    for k in a:
        assert a[k].shape == b[k].shape and a[k].dtype == b[k].dtype, k
        assert a[k].tobytes() == b[k].tobytes(), f"{k} differs"


def step_by_step_loop_correction(store: InMemoryMapStore, corr: LoopCorrection) -> None:
    """The correction written as it is computed (the form before the compute/write split): move each point seen
    by the corrected keyframes (once, by the first in id order), set the poses, refresh the moved points."""
    done: set[int] = set()
    for kf_id in sorted(corr.corrected):
        kf = store.get_keyframe(kf_id)
        pids = [p for p in kf.point_ids[kf.point_ids >= 0].tolist() if p not in done and store.has_point(p)]
        done.update(pids)
        M = corr.corrected[kf_id].inverse().matrix() @ corr.non_corrected[kf_id].matrix()
        if pids:
            ids = np.array(pids, np.int64)
            store.assign_points(ids, "xyz_w", store.point_rows(ids, "xyz_w") @ M[:3, :3].T + M[:3, 3])
    for kf_id, S in corr.corrected.items():
        store.set_keyframe_pose(kf_id, pose_of_sim3(S))
    refresh_points(store, done, normals=True, descriptors=False)


def step_by_step_essential_graph(
    store: InMemoryMapStore, S_before: np.ndarray, result: EssentialGraphResult, kf_ids: list[int]
) -> None:
    """apply_essential_graph written as it is computed: the points moved with their reference keyframe (one
    product per keyframe, as the arithmetic of a (P, 3) product may depend on P), the poses set, then every point
    refreshed."""
    row = {k: i for i, k in enumerate(kf_ids)}
    by_ref: dict[int, list[int]] = {}
    for pid in store.point_ids():
        by_ref.setdefault(store.get_point(pid).ref_kf_id, []).append(pid)
    for ref, pids in by_ref.items():
        M = Sim3.from_matrix(result.S_c_w[row[ref]]).inverse().matrix() @ S_before[row[ref]]
        ids = np.array(pids, np.int64)
        store.assign_points(ids, "xyz_w", store.point_rows(ids, "xyz_w") @ M[:3, :3].T + M[:3, 3])
    for k in kf_ids:
        store.set_keyframe_pose(k, pose_of_sim3(Sim3.from_matrix(result.S_c_w[row[k]])))
    refresh_points(store, store.point_ids(), normals=True, descriptors=False)


def test_computed_then_written_corrections_equal_the_step_by_step_ones_bit_for_bit() -> None:
    a, b = line_map(), line_map()
    assert_same_bits(snapshot(a), snapshot(b))
    S_cw = loop_sim3(a)
    corr_a, corr_b = propagate_loop_sim3(a, N - 1, S_cw), propagate_loop_sim3(b, N - 1, S_cw)
    assert len(corr_a.corrected) >= 2  # the current keyframe and its neighbour
    apply_loop_correction(a, corr_a)
    step_by_step_loop_correction(b, corr_b)
    after_a = snapshot(a)
    assert_same_bits(after_a, snapshot(b))
    assert not np.array_equal(after_a["poses"][-1], line_map().get_keyframe(N - 1).T_c_w)  # the correction moved it

    problem, kf_ids = essential_graph_problem(a, 0, N - 1, corr_a, {N - 1: {0}}, 15)
    result = optimized(problem.S_c_w)
    apply_essential_graph(a, problem, result, kf_ids)
    step_by_step_essential_graph(b, problem.S_c_w, result, kf_ids)
    assert_same_bits(snapshot(a), snapshot(b))
    assert not np.array_equal(snapshot(a)["xyz_w"], after_a["xyz_w"])  # the essential graph moved the points


def _reader_gets_in(store: InMemoryMapStore, timeout_s: float) -> bool:
    """Whether another thread (tracking) takes the map's read lock within timeout_s."""
    got = threading.Event()

    def read() -> None:
        with store.read():
            got.set()

    t = threading.Thread(target=read, daemon=True)
    t.start()
    entered = got.wait(timeout_s)
    return entered


@pytest.fixture
def closer() -> Iterator[tuple[loop_closing.LoopCloser, InMemoryMapStore]]:
    store = line_map()
    registry = ComponentRegistry.discover()
    optimizer = registry.instantiate("optimizer", {"_target_": registry.get("optimizer", "scipy").spec.target})
    cfg = LoopClosingConfig(global_ba=False, theta_min=15)
    yield loop_closing.LoopCloser(cfg, Atlas(None, first=store), optimizer, None, np.random.default_rng(0)), store  # type: ignore[arg-type]


def test_tracking_reads_the_map_while_the_correction_computes_and_waits_while_it_writes(
    closer: tuple[loop_closing.LoopCloser, InMemoryMapStore], monkeypatch: pytest.MonkeyPatch
) -> None:
    lc, store = closer
    seen: dict[str, list[bool]] = {"compute": [], "write": []}
    compute_eg, compute_lc, write = (
        loop_closing.essential_graph_move,
        loop_closing.loop_correction_move,
        loop_closing.write_map_move,
    )

    def computing(fn):  # type: ignore[no-untyped-def]
        def wrapped(*args, **kwargs):  # type: ignore[no-untyped-def]
            seen["compute"].append(_reader_gets_in(store, 5.0))  # a concurrent tracking step proceeds
            return fn(*args, **kwargs)

        return wrapped

    def writing(s, move):  # type: ignore[no-untyped-def]
        seen["write"].append(_reader_gets_in(store, 0.2))  # a concurrent tracking step waits
        write(s, move)

    monkeypatch.setattr(loop_closing, "essential_graph_move", computing(compute_eg))
    monkeypatch.setattr(loop_closing, "loop_correction_move", computing(compute_lc))
    monkeypatch.setattr(loop_closing, "write_map_move", writing)
    kf = store.get_keyframe(N - 1)
    before = snapshot(store)
    lc._correct(kf, 0, loop_sim3(store), {}, LoopOutcome(kf.id))
    assert seen == {"compute": [True, True], "write": [False, False]}
    assert not np.array_equal(snapshot(store)["poses"], before["poses"])
    assert (N - 1, 0) in store.loop_edges() or (0, N - 1) in store.loop_edges()


def test_the_correction_gives_the_same_map_with_tracking_reading_throughout(
    closer: tuple[loop_closing.LoopCloser, InMemoryMapStore],
) -> None:
    """A tracking thread reading the map (and counting visible points, as tracking does under the read lock) all
    through the correction leaves the corrected map as a correction alone makes it."""
    lc, store = closer
    alone = line_map()
    lc_alone = loop_closing.LoopCloser(lc.cfg, Atlas(None, first=alone), lc.optimizer, None, np.random.default_rng(0))  # type: ignore[arg-type]
    lc_alone._correct(alone.get_keyframe(N - 1), 0, loop_sim3(alone), {}, LoopOutcome(N - 1))

    stop = threading.Event()
    reads = [0]

    def track() -> None:
        ids = np.array(store.point_ids(), np.int64)
        while not stop.is_set():
            with store.read():
                store.point_rows(ids, "xyz_w")
                store.increase_visible(ids[:10])
                reads[0] += 1

    t = threading.Thread(target=track, daemon=True)
    t.start()
    try:
        lc._correct(store.get_keyframe(N - 1), 0, loop_sim3(store), {}, LoopOutcome(N - 1))
    finally:
        stop.set()
        t.join(5.0)
    assert reads[0] > 0
    assert_same_bits(snapshot(store), snapshot(alone))


class _CountingStore(InMemoryMapStore):
    """A map whose write counter a test can move (as another writer's write would)."""

    extra = 0

    @property
    def write_count(self) -> int:
        return super().write_count + self.extra


def test_read_then_write_prepares_again_under_the_write_lock_when_another_writer_got_in() -> None:
    store = _CountingStore()
    calls: list[bool] = []  # per prepare(): whether it ran under the write lock

    def prepare() -> int:
        calls.append(not _reader_gets_in(store, 0.2))
        if len(calls) == 1:
            store.extra += 1  # someone writes between the read and the write phase
        return len(calls)

    assert read_then_write(store, prepare, lambda n: n * 10) == 20
    assert calls == [False, True]
    # nobody writing in between: prepared once, under the read lock
    calls.clear()
    store.extra = 0

    def prepare_once() -> int:
        calls.append(not _reader_gets_in(store, 0.2))
        return 1

    assert read_then_write(store, prepare_once, str) == "1"
    assert calls == [False]


def test_a_store_without_a_write_counter_computes_under_the_write_lock() -> None:
    store = InMemoryMapStore()

    class Plain:
        """A third-party store: read/write locks, no write_count."""

        def read(self):  # type: ignore[no-untyped-def]
            return store.read()

        def write(self):  # type: ignore[no-untyped-def]
            return store.write()

    under_write = read_then_write(Plain(), lambda: not _reader_gets_in(store, 0.2), lambda x: x)  # type: ignore[arg-type]
    assert under_write
