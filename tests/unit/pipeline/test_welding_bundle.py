"""The merge's welding BA (ORB-SLAM3 LoopClosing::MergeLocal -> Optimizer::LocalBundleAdjustment(pMainKF, vpAdjustKF,
vpFixedKF), slamkit/pipeline/map_merging.py ``welding_bundle``): the current window is adjusted to the matched
window alone. ORB-SLAM3 adds an observation to that BA only when its keyframe is in one of the two windows
(``pKF->mnBALocalForMerge != pMainKF->mnId`` -> skipped), so the active map's keyframes outside the current window,
which the rigid move left with the detection's error, do not hold the window back from the matched map."""

from __future__ import annotations

import numpy as np
from omegaconf import OmegaConf

from slamkit.config import compose_config
from slamkit.features import Features, Observations
from slamkit.geometry.camera import PinholeCamera
from slamkit.geometry.se3 import invert_T
from slamkit.geometry.so3 import so3_exp
from slamkit.map.entities import KeyFrame, MapPoint
from slamkit.map.store import InMemoryMapStore
from slamkit.optim.factory import build_optimizer
from slamkit.pipeline.bundle import run_bundle
from slamkit.pipeline.config import PipelineConfig
from slamkit.pipeline.map_merging import welding_bundle
from slamkit.pipeline.map_points import update_normal_and_depth
from slamkit.plugins import ComponentRegistry

CAMERA = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)
N_POINTS = 300


def pose_at(x: float, y: float = 0.0) -> np.ndarray:
    """T_c_w of a camera at (x, y, 0) looking along +y (world z up, camera y down)."""
    T_w_c = np.eye(4)
    T_w_c[:3, :3] = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    T_w_c[:3, 3] = [x, y, 0.0]
    return invert_T(T_w_c)


def rotation_deg(T_a: np.ndarray, T_b: np.ndarray) -> float:
    """Angle of the relative rotation of two poses, degrees."""
    R = T_a[:3, :3] @ T_b[:3, :3].T
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def build_map() -> tuple[InMemoryMapStore, list[int], list[int], list[int]]:
    """One map after a merge's rigid move and fusion: a wall of points at y = 4 m (true positions) seen by three
    keyframes of the matched map's window (true poses), five of the current window and three more keyframes of the
    active map outside the current window. The rigid move left the active map's keyframes turned by 0.2 degrees
    (the detection's error, ~1.7 px: inliers of every chi-square gate). Returns the store and the matched window's,
    the current window's and the outer keyframes' ids."""
    rng = np.random.default_rng(0)
    xyz = np.column_stack([rng.uniform(-1.6, 1.6, N_POINTS), np.full(N_POINTS, 4.0), rng.uniform(-1, 1, N_POINTS)])
    xyz[:, 1] += rng.uniform(-0.3, 0.3, N_POINTS)  # depth spread: the poses are well determined
    desc = rng.integers(0, 256, (N_POINTS, 32), dtype=np.uint8)
    store = InMemoryMapStore()
    error = np.eye(4)
    error[:3, :3] = so3_exp(np.array([np.radians(0.2), 0.0, 0.0]))

    def keyframe(T_true: np.ndarray, T_stored: np.ndarray) -> int:
        xyz_c = xyz @ T_true[:3, :3].T + T_true[:3, 3]
        uv = ((xyz_c[:, :2] / xyz_c[:, 2:]) * 500.0 + np.array([320.0, 240.0])).astype(np.float32)
        zeros = np.zeros(N_POINTS, np.float32)
        feats = Features(uv, uv, np.zeros(N_POINTS, np.int32), zeros, np.ones(N_POINTS, np.float32), desc, 1.2, 8)
        record = Observations.monocular(feats, CAMERA.unproject_image(uv.astype(np.float64)))
        kf = KeyFrame(store.new_keyframe_id(), 0, 0.0, T_stored, CAMERA, record, np.full(N_POINTS, -1))
        store.add_keyframe(kf)
        return kf.id

    matched = [keyframe(pose_at(x), pose_at(x)) for x in (-0.2, 0.0, 0.2)]
    current = [keyframe(pose_at(x, 0.3), error @ pose_at(x, 0.3)) for x in (-0.1, 0.0, 0.1, 0.2, 0.3)]
    outer = [keyframe(pose_at(x, 0.6), error @ pose_at(x, 0.6)) for x in (0.4, 0.5, 0.6)]
    pids = [store.new_point_id() for _ in range(N_POINTS)]
    for i, pid in enumerate(pids):
        store.add_point(MapPoint(pid, xyz[i].copy(), desc[i].copy(), matched[0], matched[0]))
        for k in [*matched, *current, *outer]:
            store.add_observation(pid, k, i)
    keyframes = {k: store.get_keyframe(k) for k in store.keyframe_ids()}
    for pid in pids:
        update_normal_and_depth(store, store.get_point(pid), keyframes)
    for k in store.keyframe_ids():
        store.update_connections(k)
    return store, matched, current, outer


def test_the_welding_ba_brings_the_current_window_onto_the_matched_map_whatever_the_rest_of_the_active_map() -> None:
    """The outer keyframes see the window's points but belong to neither window: they are not in the welding BA
    (ORB-SLAM3), so the current window lands at its true pose in the matched map's frame. Held fixed in it (the
    local-mapping BA's rule, before), they kept the window and the points half-way (~0.1 degree off)."""
    store, matched, current, outer = build_map()
    cfg = PipelineConfig.from_node(OmegaConf.to_container(compose_config().pipeline, resolve=True))  # type: ignore[arg-type]
    lc = cfg.loop_closing
    optimizer = build_optimizer(compose_config().optimizer, ComponentRegistry.discover())
    outer_before = {k: store.get_keyframe(k).T_c_w.copy() for k in outer}
    snap = welding_bundle(
        store,
        current,
        matched,
        lc.merge_ba_iterations_first,
        lc.merge_ba_iterations_second,
        lc.chi2.mono,
        lc.chi2.stereo,
    )
    assert snap is not None
    assert set(snap.kf_ids.tolist()) == set(current) | set(matched)
    run_bundle(store, optimizer, snap)
    xs = (-0.1, 0.0, 0.1, 0.2, 0.3)
    for k, x in zip(current, xs, strict=True):
        T = store.get_keyframe(k).T_c_w
        assert rotation_deg(T, pose_at(x, 0.3)) < 0.01, k
        assert np.linalg.norm(invert_T(T)[:3, 3] - [x, 0.3, 0.0]) < 1e-3, k
    for k in outer:  # not in the BA: the essential graph after it carries the window's correction to them
        assert np.array_equal(store.get_keyframe(k).T_c_w, outer_before[k])
    for k in matched:
        assert np.allclose(store.get_keyframe(k).T_c_w, pose_at((-0.2, 0.0, 0.2)[matched.index(k)]))
