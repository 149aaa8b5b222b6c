"""Loop correction on a keyframe graph with accumulated drift: propagating the loop's Sim3 and optimizing the
essential graph brings the keyframes back to the truth."""

from __future__ import annotations

import numpy as np
import pytest

from slamkit.features import Features, Observations
from slamkit.geometry.camera import PinholeCamera
from slamkit.geometry.se3 import invert_T
from slamkit.geometry.sim3 import Sim3
from slamkit.geometry.so3 import so3_exp
from slamkit.map.entities import KeyFrame, MapPoint
from slamkit.map.store import InMemoryMapStore
from slamkit.pipeline.loop_correction import (
    apply_essential_graph,
    apply_loop_correction,
    essential_graph_problem,
    propagate_loop_sim3,
)
from slamkit.plugins import ComponentRegistry

N = 40
CAMERA = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)


def _record(features: Features) -> Observations:
    """The monocular observation record of hand-made features (bearings through CAMERA)."""
    return Observations.monocular(features, CAMERA.unproject_image(features.uv_undist_px.astype(np.float64)))


#: Shared points of consecutive keyframes and of keyframes two apart (the covisibility weights).
NEAR, FAR = 150, 40
N_FEATS = 2 * (NEAR + FAR)
FEATURES = _record(
    Features(
        np.zeros((N_FEATS, 2), np.float32),
        np.zeros((N_FEATS, 2), np.float32),
        np.zeros(N_FEATS, np.int32),
        np.zeros(N_FEATS, np.float32),
        np.zeros(N_FEATS, np.float32),
        np.zeros((N_FEATS, 32), np.uint8),
        1.2,
        8,
    )
)


def true_poses() -> list[np.ndarray]:
    """T_c_w of N cameras on a circle of radius 5 m, looking outwards (z up world, camera y down)."""
    out = []
    for k in range(N):
        a = 2 * np.pi * k / N
        z_c = np.array([np.cos(a), np.sin(a), 0.0])
        y_c = np.array([0.0, 0.0, -1.0])
        x_c = np.cross(y_c, z_c)
        T_w_c = np.eye(4)
        T_w_c[:3, :3] = np.stack([x_c, y_c, z_c], axis=1)
        T_w_c[:3, 3] = 5.0 * z_c
        out.append(invert_T(T_w_c))
    return out


def drifted(truth: list[np.ndarray]) -> list[np.ndarray]:
    """Odometry with 1% scale growth and 0.3 deg yaw error per step, starting exactly at the truth."""
    est = [truth[0].copy()]
    for k in range(1, N):
        rel = truth[k] @ invert_T(truth[k - 1])  # T_k_{k-1}
        rel = rel.copy()
        rel[:3, 3] *= 1.01**k
        rel[:3, :3] = so3_exp(np.array([0.0, np.radians(0.3), 0.0])) @ rel[:3, :3]
        est.append(rel @ est[-1])
    return est


def centres(poses: list[np.ndarray]) -> np.ndarray:
    return np.stack([invert_T(T)[:3, 3] for T in poses])


def graph_map(est: list[np.ndarray]) -> InMemoryMapStore:
    """Keyframes at the drifted poses, inserted in order as local mapping does: each shares NEAR points with the
    keyframe before it and FAR with the one two before, so its spanning-tree parent is the one before it."""
    store = InMemoryMapStore()
    used = [0] * N
    for k in range(N):
        kf_id = store.new_keyframe_id()
        store.add_keyframe(KeyFrame(kf_id, k, float(k), est[k], CAMERA, FEATURES, np.full(N_FEATS, -1, np.int64)))
        for j, count in ((k - 1, NEAR), (k - 2, FAR)):
            for _ in range(count if j >= 0 else 0):
                pid = store.new_point_id()
                store.add_point(MapPoint(pid, np.zeros(3), np.zeros(32, np.uint8), j, j))  # positions play no part
                for o in (j, k):
                    store.add_observation(pid, o, used[o])
                    used[o] += 1
        store.update_connections(kf_id)
    return store


@pytest.mark.parametrize("backend", ["scipy", "gtsam"])
def test_loop_correction_and_essential_graph_remove_the_drift(backend: str) -> None:
    truth = true_poses()
    est = drifted(truth)
    store = graph_map(est)
    assert [store.covisibility.weight(k, k + 1) for k in range(N - 1)] == [NEAR] * (N - 1)
    assert [store.covisibility.weight(k, k + 2) for k in range(N - 2)] == [FAR] * (N - 2)
    assert [store.spanning_tree.parent(k) for k in range(N)] == [None, *range(N - 1)]
    before = np.linalg.norm(centres([store.get_keyframe(k).T_c_w for k in range(N)]) - centres(truth), axis=1)
    assert before.max() > 1.0  # the drift is large

    # the loop: the last keyframe sees keyframe 0 again. The loop's Sim3 puts it at its true place and carries the
    # scale of its local map, which drifted to sigma times the truth's (as a Sim3 from loop detection does)
    current, loop_kf = N - 1, 0
    sigma = 1.01**current
    S_cw = Sim3(sigma, truth[current][:3, :3], sigma * truth[current][:3, 3])
    corr = propagate_loop_sim3(store, current, S_cw)
    assert set(corr.corrected) == {current, current - 1, current - 2}
    apply_loop_correction(store, corr)
    np.testing.assert_allclose(store.get_keyframe(current).T_c_w, truth[current], atol=1e-9)
    registry = ComponentRegistry.discover()
    optimizer = registry.instantiate("optimizer", {"_target_": registry.get("optimizer", backend).spec.target})
    problem, kf_ids = essential_graph_problem(store, loop_kf, current, corr, {current: {loop_kf}}, 100)
    # spanning tree (N - 1) + the loop edge; the weight-40 edges are below theta_min
    assert list(zip(problem.edge_i.tolist(), problem.edge_j.tolist(), strict=True)) == sorted(
        [(k, k + 1) for k in range(N - 1)] + [(loop_kf, current)]
    )
    apply_essential_graph(store, problem, optimizer.optimize_essential_graph(problem), kf_ids)
    after = np.linalg.norm(centres([store.get_keyframe(k).T_c_w for k in range(N)]) - centres(truth), axis=1)
    np.testing.assert_allclose(store.get_keyframe(loop_kf).T_c_w, est[0], atol=1e-9)  # the loop keyframe is fixed
    # with the drift spread over the graph, every keyframe is back within a few centimetres (drift was metres)
    assert after.max() < 0.05 * before.max()
    assert np.sqrt(np.mean(after**2)) < 0.05 * np.sqrt(np.mean(before**2))
