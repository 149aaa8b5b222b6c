"""Global BA after a loop (ORB-SLAM2 RunGlobalBundleAdjustment): what was added while it ran follows its
correction through the spanning tree; it removes no observation; an aborted one writes nothing."""

from __future__ import annotations

import threading

import numpy as np

from slamkit.config import compose_config
from slamkit.features import Features, Observations
from slamkit.geometry.camera import PinholeCamera
from slamkit.geometry.se3 import invert_T
from slamkit.geometry.so3 import so3_exp
from slamkit.map.entities import KeyFrame, MapPoint
from slamkit.map.store import InMemoryMapStore
from slamkit.optim.factory import build_optimizer
from slamkit.pipeline.global_ba import commit_global_ba, optimize_global_ba, snapshot_global_ba
from slamkit.pipeline.map_points import update_normal_and_depth
from slamkit.plugins import ComponentRegistry
from slamkit.problems import BundleResult

CAMERA = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)
N = 200


def pose_at(x: float) -> np.ndarray:
    """T_c_w of a camera at (x, 0, 0) looking along +y (world z up, camera y down)."""
    T_w_c = np.eye(4)
    T_w_c[:3, :3] = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    T_w_c[:3, 3] = [x, 0.0, 0.0]
    return invert_T(T_w_c)


class Scene:
    """Points in front of the cameras (3-6 m deep); keyframes seeing chosen points with exact observations."""

    def __init__(self) -> None:
        rng = np.random.default_rng(0)
        self.xyz = np.column_stack([rng.uniform(-2, 2, N), rng.uniform(3, 6, N), rng.uniform(-1.5, 1.5, N)])
        self.desc = rng.integers(0, 256, (N, 32), dtype=np.uint8)
        self.store = InMemoryMapStore()
        self.pids = [self.store.new_point_id() for _ in range(N)]

    def add_keyframe(self, T_c_w: np.ndarray, seen: range) -> int:
        xyz_c = self.xyz @ T_c_w[:3, :3].T + T_c_w[:3, 3]
        uv = ((xyz_c[:, :2] / xyz_c[:, 2:]) * 500.0 + np.array([320.0, 240.0])).astype(np.float32)
        feats = Features(uv, uv, np.zeros(N, np.int32), np.zeros(N, np.float32), np.ones(N, np.float32),
                         self.desc.copy(), 1.2, 8)  # fmt: skip
        obs = Observations.monocular(feats, CAMERA.unproject_image(uv.astype(np.float64)))
        store = self.store
        kf = KeyFrame(store.new_keyframe_id(), store.n_keyframes(), 0.0, T_c_w.copy(), CAMERA, obs, np.full(N, -1))
        store.add_keyframe(kf)
        for i in seen:
            if not store.has_point(self.pids[i]):
                store.add_point(MapPoint(self.pids[i], self.xyz[i].copy(), self.desc[i].copy(), kf.id, kf.id))
            store.add_observation(self.pids[i], kf.id, i)
        store.update_connections(kf.id)
        return kf.id

    def refresh(self) -> None:
        keyframes = {k: self.store.get_keyframe(k) for k in self.store.keyframe_ids()}
        for pid in self.store.point_ids():
            update_normal_and_depth(self.store, self.store.get_point(pid), keyframes)


def test_keyframes_and_points_added_meanwhile_follow_the_correction_through_the_spanning_tree() -> None:
    scene = Scene()
    store = scene.store
    k0 = scene.add_keyframe(pose_at(0.0), range(0, 150))
    k1 = scene.add_keyframe(pose_at(0.3), range(0, 190))
    scene.refresh()
    snap = snapshot_global_ba(store, 10, 5.991, 7.815)
    assert snap is not None and snap.kf_ids.tolist() == [k1, k0] and snap.problem.iterations_second == 0
    # while the BA runs: a keyframe sharing points only with k1 (its spanning-tree parent) and a point it made
    k2 = scene.add_keyframe(pose_at(0.6), range(150, 200))
    assert store.spanning_tree.parent(k2) == k1
    new_pid = scene.pids[195]
    assert store.get_point(new_pid).ref_kf_id == k2
    T1, T2 = store.get_keyframe(k1).T_c_w.copy(), store.get_keyframe(k2).T_c_w.copy()
    x_new_c2 = T2[:3, :3] @ store.get_point(new_pid).xyz_w + T2[:3, 3]
    # the BA's result: k1 turned and moved (what a global BA after a loop does to a drifted keyframe)
    D = np.eye(4)
    D[:3, :3], D[:3, 3] = so3_exp(np.array([0.0, 0.02, 0.01])), [0.05, -0.02, 0.1]
    T_new = snap.problem.T_c_w.copy()
    T_new[0] = D @ T1
    result = BundleResult(T_new, snap.problem.xyz_w.copy(), np.zeros(snap.problem.obs_pose.size, bool), 0, 0, 1)
    with store.write():
        assert commit_global_ba(store, snap, result) == (1, 10)  # k2; points 190..199 (not in the snapshot)
    np.testing.assert_allclose(store.get_keyframe(k1).T_c_w, D @ T1, atol=1e-12)
    # k2 keeps its pose relative to its parent as it was before the correction
    np.testing.assert_allclose(store.get_keyframe(k2).T_c_w, T2 @ invert_T(T1) @ D @ T1, atol=1e-12)
    # the point k2 made stays where k2 sees it
    T2n = store.get_keyframe(k2).T_c_w
    np.testing.assert_allclose(T2n[:3, :3] @ store.get_point(new_pid).xyz_w + T2n[:3, 3], x_new_c2, atol=1e-9)


def test_a_global_ba_removes_no_observation_and_an_aborted_one_is_flagged() -> None:
    scene = Scene()
    store = scene.store
    scene.add_keyframe(pose_at(0.0), range(N))
    k1 = scene.add_keyframe(pose_at(0.3), range(N))
    k2 = scene.add_keyframe(pose_at(0.6), range(N))
    scene.refresh()
    # drift: k2 off by 5 cm along x
    store.set_keyframe_poses(
        [k2], (store.get_keyframe(k2).T_c_w @ invert_T(pose_at(0.05) @ invert_T(pose_at(0.0))))[None]
    )
    n_obs = sum(len(store.get_point(p).observations) for p in store.point_ids())
    cfg = compose_config()
    optimizer = build_optimizer(cfg.optimizer, ComponentRegistry.discover())
    snap = snapshot_global_ba(store, 10, 5.991, 7.815)
    assert snap is not None
    stop = threading.Event()
    stop.set()
    assert optimize_global_ba(optimizer, snap, stop).aborted
    result = optimize_global_ba(optimizer, snap, None)
    assert not result.aborted and not result.outlier.any()
    with store.write():
        commit_global_ba(store, snap, result)
    assert sum(len(store.get_point(p).observations) for p in store.point_ids()) == n_obs
    # the map is consistent again: k2 back at 0.3 m from k1 (scale fixed by k0 and k1)
    c1 = invert_T(store.get_keyframe(k1).T_c_w)[:3, 3]
    c2 = invert_T(store.get_keyframe(k2).T_c_w)[:3, 3]
    assert abs(np.linalg.norm(c2 - c1) - 0.3) < 0.01
