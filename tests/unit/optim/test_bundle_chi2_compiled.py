"""slamkit.optim.costs.bundle_chi2's compiled pass for one-camera pinhole problems against the numpy formula it replaces
(``_reprojection_chi2`` on per-observation gathers), to the bit: the reported costs of every backend read it."""

from __future__ import annotations

import numpy as np
import pytest

from slamkit.optim.costs import _reprojection_chi2, bundle_chi2, bundle_cost
from slamkit.problems import BundleProblem


def _numpy_chi2(problem: BundleProblem, T_c_w: np.ndarray, xyz_w: np.ndarray) -> np.ndarray:
    T = T_c_w[problem.obs_pose]
    return _reprojection_chi2(
        T[:, :3, :3],
        T[:, :3, 3],
        xyz_w[problem.obs_point],
        problem.uv_px,
        problem.u_right_px,
        problem.level.astype(np.float64),
        problem.intrinsics[problem.obs_pose],
        problem.bf[problem.obs_pose],
        problem.scale_factor,
        None,
    )


def _problem(seed: int, stereo_share: float) -> BundleProblem:
    rng = np.random.default_rng(seed)
    K, M, E = 5, 300, 1200
    T = np.tile(np.eye(4), (K, 1, 1))
    for k in range(K):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)) * 0.05 + np.eye(3))
        T[k, :3, :3] = q * np.sign(np.linalg.det(q))
        T[k, :3, 3] = rng.normal(0, 0.2, 3)
    xyz = rng.normal(0, 1.0, (M, 3)) + np.array([0.0, 0.0, 3.0])
    xyz[:4, 2] = -3.0  # behind the cameras: chi2 inf
    uv = rng.uniform(0, 640, (E, 2))
    return BundleProblem(
        T_c_w=T,
        pose_fixed=np.arange(K) == 0,
        intrinsics=np.tile([517.3, 516.5, 318.6, 255.3], (K, 1)) * rng.uniform(0.99, 1.01, (K, 4)),
        bf=np.full(K, 40.0),
        xyz_w=xyz,
        point_fixed=np.zeros(M, bool),
        obs_pose=rng.integers(0, K, E).astype(np.int64),
        obs_point=rng.integers(0, M, E).astype(np.int64),
        uv_px=uv,
        u_right_px=np.where(rng.random(E) < stereo_share, uv[:, 0] - rng.uniform(1, 30, E), np.nan),
        level=rng.integers(0, 8, E).astype(np.int64),
        scale_factor=1.2,
    )


@pytest.mark.parametrize(("seed", "stereo_share"), [(0, 0.0), (1, 0.4), (2, 1.0)])
def test_compiled_bundle_chi2_is_the_numpy_formula_to_the_bit(seed: int, stereo_share: float) -> None:
    problem = _problem(seed, stereo_share)
    rng = np.random.default_rng(seed + 10)
    xyz = problem.xyz_w + rng.normal(0, 0.01, problem.xyz_w.shape)
    got = bundle_chi2(problem, problem.T_c_w, xyz)
    want = _numpy_chi2(problem, problem.T_c_w, xyz)
    assert np.isinf(got).any() and np.isfinite(got).any()
    assert np.array_equal(got.view(np.int64), want.view(np.int64))
    active = rng.random(got.size) < 0.8
    assert bundle_cost(problem, problem.T_c_w, xyz, active) > 0.0
