"""ORB-SLAM2's PnPsolver as slamkit's relocalization uses it: the pose of a camera from 3D-2D matches with outliers,
an inlier gate scaled by each keypoint's level, and its RANSAC parameters (SetRansacParameters(0.99, 10, 300, 4,
0.5, 5.991))."""

from __future__ import annotations

import numpy as np

from slamkit.geometry.so3 import so3_exp
from slamkit.pipeline.tracking.relocalization import PnPRansac

K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])


def _scene(n: int, outliers: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    T = np.eye(4)
    T[:3, :3] = so3_exp(np.array([0.05, -0.1, 0.02]))
    T[:3, 3] = [0.1, -0.05, 0.3]
    xyz_c = np.c_[rng.uniform(-1, 1, (n, 2)), rng.uniform(2, 5, n)]
    xyz_w = (xyz_c - T[:3, 3]) @ T[:3, :3]  # R^T (x - t)
    uv = xyz_c[:, :2] / xyz_c[:, 2:3] @ K[:2, :2].T + K[:2, 2] + rng.normal(0, 0.5, (n, 2))
    uv[:outliers] += rng.uniform(30, 80, (outliers, 2))
    return T, xyz_w, uv, np.ones(n)


def _solver(xyz: np.ndarray, uv: np.ndarray, sigma2: np.ndarray) -> PnPRansac:
    return PnPRansac(xyz, uv, sigma2, K, 5.991, 0.99, 10, 300, 4, 0.5)


def test_pnp_ransac_recovers_the_pose_and_rejects_the_outliers() -> None:
    rng = np.random.default_rng(0)
    T, xyz, uv, sigma2 = _scene(100, 30, rng)
    solver = _solver(xyz, uv, sigma2)
    found = None
    while found is None and not solver.exhausted():
        found = solver.iterate(5, rng)
    assert found is not None
    T_est, inliers = found
    assert np.abs(T_est[:3, 3] - T[:3, 3]).max() < 0.02
    assert np.abs(T_est[:3, :3] - T[:3, :3]).max() < 0.01
    assert not inliers[:30].any() and inliers[30:].sum() >= 65


def test_ransac_parameters_as_orbslam2_sets_them() -> None:
    rng = np.random.default_rng(1)
    _, xyz, uv, sigma2 = _scene(100, 0, rng)
    solver = _solver(xyz, uv, sigma2)
    assert solver.needed == 50  # max(10, 0.5 N, 4)
    assert solver.iterations == 35  # ceil(log(0.01) / log(1 - 0.5^3))
    few = _solver(xyz[:12], uv[:12], sigma2[:12])
    assert few.needed == 10 and few.iterations == min(300, int(np.ceil(np.log(0.01) / np.log(1 - (10 / 12) ** 3))))


def test_the_inlier_gate_scales_with_the_keypoint_level() -> None:
    rng = np.random.default_rng(2)
    T, xyz, uv, _ = _scene(60, 0, rng)
    uv = uv.copy()
    uv[:10] += 3.0  # 4.2 px off: an outlier at level 0 (gate 2.45 px), an inlier at level 5 of 1.2 (gate 6.1 px)
    level0 = _solver(xyz, uv, np.ones(60))
    coarse = _solver(xyz, uv, np.r_[np.full(10, 1.2**10), np.ones(50)])
    assert not level0._inliers(T)[:10].any()
    assert coarse._inliers(T)[:10].all()
