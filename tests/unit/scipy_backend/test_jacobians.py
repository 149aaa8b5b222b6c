"""Analytic Jacobians of the SciPy backend against central finite differences.

Each solver's linearization returns g = J^T W r with IRLS Huber weights; since d rho(chi2) = rho' d chi2
the exact gradient of its robust cost is 2 g, so comparing 2 g with a numeric gradient of the cost checks
Jacobians, weights and the retraction together (with outliers in the Huber tail included).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from slamkit_scipy.bundle import BAState, BundleSolver, _Stage
from slamkit_scipy.lie import se3_exp_batch, sim3_exp_batch
from slamkit_scipy.pose_graph import PoseGraphSolver, edge_errors, edge_jacobians
from slamkit_scipy.pose_only import linearize_pose, retract_pose, robust_cost
from slamkit_scipy.reprojection import Observations, make_observations, pose_jacobian, projection_jacobian, residuals
from slamkit_scipy.robust import inv_sigma2
from slamkit_scipy.sim3_align import _cost, _Matches, linearize_sim3, retract_sim3

from slamkit.optim import synthetic as syn


def numeric_gradient(f: Callable[[np.ndarray], float], n: int, h: float = 1e-6) -> np.ndarray:
    out = np.zeros(n)
    for a in range(n):
        d = np.zeros(n)
        d[a] = h
        out[a] = (f(d) - f(-d)) / (2 * h)
    return out


def _observations(rng: np.random.Generator, n: int, stereo: bool) -> tuple[np.ndarray, Observations]:
    X_c = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(2, 8, n)])
    uv = rng.uniform(0, 640, (n, 2))
    u_r = uv[:, 0] - rng.uniform(1, 30, n) if stereo else np.full(n, np.nan)
    obs = make_observations(
        uv, u_r, np.tile([450.0, 460.0, 320.0, 240.0], (n, 1)), np.full(n, 40.0), np.ones(n), 5.991, 7.815
    )
    return X_c, obs


@pytest.mark.parametrize("stereo", [False, True])
def test_reprojection_jacobians(stereo: bool) -> None:
    rng = np.random.default_rng(0)
    X_c, obs = _observations(rng, 6, stereo)
    T = se3_exp_batch(rng.normal(0, 0.1, (1, 6)))[0]
    X_w = (X_c - T[:3, 3]) @ T[:3, :3]  # world points that land on X_c
    p_c = X_w @ T[:3, :3].T + T[:3, 3]
    A = projection_jacobian(p_c, obs)
    Jpose = pose_jacobian(p_c, A)
    Jpoint = A @ T[:3, :3]
    h = 1e-6
    for a in range(6):
        d = np.zeros(6)
        d[a] = h
        rp = residuals(X_w @ (se3_exp_batch(d[None])[0] @ T)[:3, :3].T + (se3_exp_batch(d[None])[0] @ T)[:3, 3], obs)
        rm = residuals(X_w @ (se3_exp_batch(-d[None])[0] @ T)[:3, :3].T + (se3_exp_batch(-d[None])[0] @ T)[:3, 3], obs)
        np.testing.assert_allclose(Jpose[:, :, a], (rp - rm) / (2 * h), rtol=1e-5, atol=1e-5)
    for a in range(3):
        d = np.zeros(3)
        d[a] = h
        rp = residuals((X_w + d) @ T[:3, :3].T + T[:3, 3], obs)
        rm = residuals((X_w - d) @ T[:3, :3].T + T[:3, 3], obs)
        np.testing.assert_allclose(Jpoint[:, :, a], (rp - rm) / (2 * h), rtol=1e-5, atol=1e-5)
    if not stereo:
        assert np.all(Jpose[:, 2] == 0.0)


@pytest.mark.parametrize("robust", [True, False])
def test_pose_only_gradient(robust: bool) -> None:
    problem, _ = syn.make_pose_problem(np.random.default_rng(1), n_points=60, stereo_ratio=0.5)
    n = len(problem.xyz_w)
    obs = make_observations(
        problem.uv_px,
        problem.u_right_px,
        np.tile(problem.intrinsics, (n, 1)),
        np.full(n, problem.bf),
        inv_sigma2(problem.level, problem.scale_factor),
        problem.chi2_mono,
        problem.chi2_stereo,
    )
    T = problem.T_c_w_init
    _, g, f, _ = linearize_pose(T, X=problem.xyz_w, obs=obs, robust=robust)
    assert f == pytest.approx(robust_cost(T, problem.xyz_w, obs, robust))
    num = numeric_gradient(lambda d: robust_cost(retract_pose(T, d), problem.xyz_w, obs, robust), 6)
    np.testing.assert_allclose(2 * g, num, rtol=1e-5, atol=1e-4 * np.abs(num).max())


def test_bundle_gradient_over_poses_and_points() -> None:
    problem, _ = syn.make_bundle_problem(
        np.random.default_rng(2), n_free=3, n_fixed=2, n_points=40, n_obs=160, stereo_ratio=0.3
    )
    op = problem.obs_pose
    obs = make_observations(
        problem.uv_px,
        problem.u_right_px,
        problem.intrinsics[op],
        problem.bf[op],
        inv_sigma2(problem.level, problem.scale_factor),
        problem.chi2_mono,
        problem.chi2_stereo,
    )
    solver = BundleSolver(_Stage(problem, obs, np.ones(op.size, dtype=bool), True), dense_max=3000)
    state = BAState(problem.T_c_w.copy(), problem.xyz_w.copy())
    _, g, f, _ = solver.linearize(state)
    assert f == pytest.approx(solver.cost(state))
    num = numeric_gradient(lambda d: solver.cost(solver.retract(state, d)), g.size)
    np.testing.assert_allclose(2 * g, num, rtol=1e-4, atol=1e-4 * np.abs(num).max())


@pytest.mark.parametrize("fix_scale", [False, True])
def test_sim3_gradient_both_directions(fix_scale: bool) -> None:
    problem, _ = syn.make_sim3_problem(np.random.default_rng(3), n_matches=50, fix_scale=fix_scale)
    m = _Matches(
        problem.xyz1_c1,
        problem.xyz2_c2,
        problem.uv1_px,
        problem.uv2_px,
        inv_sigma2(problem.level1, problem.scale_factor),
        inv_sigma2(problem.level2, problem.scale_factor),
        problem.intrinsics1,
        problem.intrinsics2,
    )
    delta = float(np.sqrt(problem.chi2))
    dof = 6 if fix_scale else 7
    S = problem.S_12_init
    _, g, f, _ = linearize_sim3(S, m=m, delta=delta, dof=dof)
    assert f == pytest.approx(_cost(S, m, delta))
    num = numeric_gradient(lambda d: _cost(retract_sim3(S, d), m, delta), dof)
    np.testing.assert_allclose(2 * g, num, rtol=1e-5, atol=1e-5 * np.abs(num).max())


def test_pose_graph_edge_jacobians_large_error() -> None:
    """The adjoint-based Jacobian with the exact J_l^-1 stays accurate for a large (fresh loop) error."""
    rng = np.random.default_rng(4)
    S = sim3_exp_batch(rng.normal(0, 1.0, (2, 7)))
    S_ij = sim3_exp_batch(rng.normal(0, 1.0, (1, 7)))
    i, j = np.array([0]), np.array([1])
    e, E = edge_errors(S, i, j, S_ij)
    assert np.abs(e).max() > 0.5
    Ji, Jj = edge_jacobians(e, E, S_ij)

    def err(k: int, d: np.ndarray) -> np.ndarray:
        S2 = S.copy()
        S2[k] = sim3_exp_batch(d[None])[0] @ S[k]
        return edge_errors(S2, i, j, S_ij)[0][0]

    for k, J in ((0, Ji[0]), (1, Jj[0])):
        num = np.column_stack([(err(k, d) - err(k, -d)) / 2e-6 for d in 1e-6 * np.eye(7)])
        np.testing.assert_allclose(J, num, atol=1e-6 * np.abs(num).max())


def test_pose_graph_edge_jacobians_small_error() -> None:
    rng = np.random.default_rng(5)
    S = sim3_exp_batch(rng.normal(0, 1.0, (2, 7)))
    S_ij = S[:1] @ np.linalg.inv(S[1:]) @ sim3_exp_batch(rng.normal(0, 0.01, (1, 7)))
    i, j = np.array([0]), np.array([1])
    e, E = edge_errors(S, i, j, S_ij)
    Ji, _ = edge_jacobians(e, E, S_ij)

    def err(d: np.ndarray) -> np.ndarray:
        S2 = S.copy()
        S2[0] = sim3_exp_batch(d[None])[0] @ S[0]
        return edge_errors(S2, i, j, S_ij)[0][0]

    num = np.column_stack([(err(d) - err(-d)) / 2e-6 for d in 1e-6 * np.eye(7)])
    np.testing.assert_allclose(Ji[0], num, atol=1e-6 * np.abs(num).max() + 1e-7)


@pytest.mark.parametrize("use_sim3", [True, False])
def test_pose_graph_gradient(use_sim3: bool) -> None:
    problem, _ = syn.make_essential_graph_problem(
        np.random.default_rng(6), n_keyframes=12, n_edges=16, use_sim3=use_sim3
    )
    solver = PoseGraphSolver(problem)
    S = problem.S_c_w
    _, g, f, _ = solver.linearize(S)
    assert f == pytest.approx(solver.cost(S))
    num = numeric_gradient(lambda d: solver.cost(solver.retract(S, d)), g.size)
    np.testing.assert_allclose(2 * g, num, rtol=1e-4, atol=1e-4 * np.abs(num).max())
