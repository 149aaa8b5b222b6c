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
from slamkit.map.entities import KeyFrame
from slamkit.map.store import InMemoryMapStore
from slamkit.pipeline.loop_correction import (
    apply_loop_correction,
    optimize_essential_graph,
    propagate_loop_sim3,
)
from slamkit.plugins import ComponentRegistry

N = 40
CAMERA = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)


def _record(features: Features) -> Observations:
    """The monocular observation record of hand-made features (bearings through CAMERA)."""
    return Observations.monocular(features, CAMERA.unproject_image(features.uv_undist_px.astype(np.float64)))


EMPTY = _record(
    Features(
        np.zeros((0, 2), np.float32),
        np.zeros((0, 2), np.float32),
        np.zeros(0, np.int32),
        np.zeros(0, np.float32),
        np.zeros(0, np.float32),
        np.zeros((0, 32), np.uint8),
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


@pytest.mark.parametrize("backend", ["scipy", "gtsam"])
def test_loop_correction_and_essential_graph_remove_the_drift(backend: str) -> None:
    truth = true_poses()
    est = drifted(truth)
    store = InMemoryMapStore()
    for k in range(N):
        kf_id = store.new_keyframe_id()
        store.add_keyframe(KeyFrame(kf_id, k, float(k), est[k].copy(), CAMERA, EMPTY, np.zeros(0, np.int64)))
    for k in range(N):
        shared = {j: (150 if abs(j - k) == 1 else 40) for j in range(max(0, k - 2), min(N, k + 3)) if j != k}
        store.covisibility.update_connections(k, shared, 15)
        store.spanning_tree.add(k, k - 1 if k > 0 else None)
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
    _, n_edges = optimize_essential_graph(store, optimizer, loop_kf, current, corr, {current: {loop_kf}}, 100)
    assert n_edges == N  # spanning tree (N - 1) + the loop edge; the weight-40 edges are below theta_min
    after = np.linalg.norm(centres([store.get_keyframe(k).T_c_w for k in range(N)]) - centres(truth), axis=1)
    np.testing.assert_allclose(store.get_keyframe(loop_kf).T_c_w, est[0], atol=1e-9)  # the loop keyframe is fixed
    # with the drift spread over the graph, every keyframe is back within a few centimetres (drift was metres)
    assert after.max() < 0.05 * before.max()
    assert np.sqrt(np.mean(after**2)) < 0.05 * np.sqrt(np.mean(before**2))
