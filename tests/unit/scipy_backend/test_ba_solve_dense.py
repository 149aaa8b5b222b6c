"""slamkit_scipy.kernels.ba_solve_dense (the LM's dense step in one compiled call) against the three kernels it
replaced in BundleSolver.solve, called one by one from Python as before: reduced system, Cholesky, finiteness test,
back-substitution, concatenation. The step must be equal to the bit (NaN everywhere for an indefinite system), and a
whole bundle adjustment through it must give the poses, points and outliers of the former solve."""

from __future__ import annotations

import numpy as np
import pytest
import slamkit_scipy.bundle as bundle
from slamkit_scipy.kernels import ba_back_substitute, ba_reduced_system, ba_solve_dense, cholesky_solve_upper
from slamkit_scipy.lm import LMSettings

from slamkit.problems import BundleProblem

F64 = np.ndarray


def _former_step(U: F64, V: F64, W: F64, gc: F64, gp: F64, lam: float, c: F64, ptr: F64, obs: F64) -> F64:
    """BundleSolver.solve's dense branch as it was (slamkit ed54e19)."""
    n, npt = 6 * U.shape[0], V.shape[0]
    S, rhs, Vinv = ba_reduced_system(U, V, W, gc, gp, lam, c, ptr, obs)  # W: ba_linearize's WT (E, 3, 8)
    dc = cholesky_solve_upper(S, rhs)
    if not np.all(np.isfinite(dc)):
        return np.full(n + 3 * npt, np.nan)
    dp = ba_back_substitute(dc, Vinv, W, gp, c, ptr, obs)
    return np.concatenate([dc, dp.ravel()])


def _system(seed: int, nc: int, npt: int, indefinite: bool = False) -> tuple:
    """A random damped Gauss-Newton system: each point seen by 1..nc poses in a random order (W's rows not in the
    points' order), U, V and W summed from random 2-row Jacobians per observation (so the reduced system is positive
    definite); ``indefinite``: U of one pose made negative definite, so the Cholesky meets a negative pivot."""
    rng = np.random.default_rng(seed)
    c_list: list[int] = []
    p_list: list[int] = []
    obs: list[int] = []
    ptr = [0]
    for q in range(npt):
        for k in rng.permutation(nc)[: rng.integers(1, nc + 1)]:
            obs.append(len(c_list))
            c_list.append(int(k))
            p_list.append(q)
        ptr.append(len(obs))
    E = len(c_list)
    order = rng.permutation(E)
    Jc = rng.normal(size=(E, 2, 6))
    Jp = rng.normal(size=(E, 2, 3))
    U = 1e-3 * np.tile(np.eye(6), (nc, 1, 1))
    V = np.zeros((npt, 3, 3))
    np.add.at(U, np.array(c_list), np.einsum("eai,eaj->eij", Jc, Jc))
    np.add.at(V, np.array(p_list), np.einsum("eai,eaj->eij", Jp, Jp))
    W = np.einsum("eai,eaj->eij", Jc, Jp)
    if indefinite:
        U[nc // 2] = -U[nc // 2] - np.eye(6)
    WT = np.zeros((E, 3, 8))  # ba_linearize's layout: W transposed, lanes 6 and 7 zero
    WT[:, :, :6] = W[np.argsort(order)].transpose(0, 2, 1)
    return (
        U,
        V,
        WT,
        rng.normal(size=(nc, 6)),
        rng.normal(size=(npt, 3)),
        float(rng.uniform(1e-3, 10.0)),
        np.array(c_list, np.int64)[np.argsort(order)],
        np.array(ptr, np.int64),
        order[np.array(obs, np.int64)].astype(np.int64),
    )


@pytest.mark.parametrize(("seed", "nc", "npt"), [(0, 1, 5), (1, 4, 40), (2, 9, 120), (3, 25, 300)])
def test_dense_step_is_the_former_solve_to_the_bit(seed: int, nc: int, npt: int) -> None:
    args = _system(seed, nc, npt)
    got = ba_solve_dense(*args)
    want = _former_step(*args)
    assert got.shape == (6 * nc + 3 * npt,)
    assert np.all(np.isfinite(want))
    assert np.array_equal(got.view(np.uint64), want.view(np.uint64))


def _back_substitute_reference(dc: F64, Vinv: F64, W: F64, gp: F64, c: F64, ptr: F64, obs: F64) -> F64:
    """dp_q = Vinv_q (-gp_q - sum_e W_e^T dc_(c_e)) in Python floats, from the (E, 6, 3) blocks W: each W_e^T dc term
    summed over k = 0..5 from 0.0, then subtracted, observation by observation (the kernel's order, no fusion)."""
    dp = np.zeros((Vinv.shape[0], 3))
    for q in range(Vinv.shape[0]):
        t = [-float(gp[q, i]) for i in range(3)]
        for e in obs[ptr[q] : ptr[q + 1]]:
            for i in range(3):
                s = 0.0
                for k in range(6):
                    s += float(W[e, k, i]) * float(dc[6 * c[e] + k])
                t[i] -= s
        for i in range(3):
            dp[q, i] = float(Vinv[q, i, 0]) * t[0] + float(Vinv[q, i, 1]) * t[1] + float(Vinv[q, i, 2]) * t[2]
    return dp


@pytest.mark.parametrize("seed", [5, 6])
def test_back_substitution_reads_the_transposed_blocks_to_the_bit(seed: int) -> None:
    """ba_back_substitute on ba_linearize's WT layout equals the reference on the (E, 6, 3) blocks, every bit."""
    U, V, WT, _, gp, lam, c, ptr, obs = _system(seed, 8, 70)
    rng = np.random.default_rng(seed)
    dc = rng.normal(size=6 * U.shape[0])
    Vinv = np.linalg.inv(V + lam * np.eye(3))
    got = ba_back_substitute(dc, Vinv, WT, gp, c, ptr, obs)
    want = _back_substitute_reference(dc, Vinv, WT[:, :, :6].transpose(0, 2, 1), gp, c, ptr, obs)
    assert np.array_equal(got.view(np.uint64), want.view(np.uint64))


def test_dense_step_of_an_indefinite_system_is_nan_everywhere() -> None:
    args = _system(4, 6, 50, indefinite=True)
    got = ba_solve_dense(*args)
    assert got.shape == (6 * 6 + 3 * 50,)
    assert np.all(np.isnan(got))
    assert np.all(np.isnan(_former_step(*args)))


def _bundle_problem(seed: int, stereo: bool) -> BundleProblem:
    """Five keyframes (the first two fixed) looking at 80 points, observations noisy by ~1 px."""
    rng = np.random.default_rng(seed)
    K, M = 5, 80
    T = np.tile(np.eye(4), (K, 1, 1))
    T[:, 0, 3] = -0.2 * np.arange(K)
    X = np.column_stack([rng.uniform(-2, 2, M), rng.uniform(-1.5, 1.5, M), rng.uniform(4, 8, M)])
    fx, fy, cx, cy, bf = 500.0, 500.0, 320.0, 240.0, 40.0
    pose, point, uv, ur = [], [], [], []
    for k in range(K):
        for j in range(M):
            p = X[j] + T[k, :3, 3]
            u, v = fx * p[0] / p[2] + cx, fy * p[1] / p[2] + cy
            pose.append(k)
            point.append(j)
            uv.append([u + rng.normal(), v + rng.normal()])
            ur.append(u - bf / p[2] + rng.normal() if stereo else np.nan)
    T_noisy = T.copy()
    T_noisy[2:, :3, 3] += rng.normal(scale=0.02, size=(K - 2, 3))
    E = len(pose)
    return BundleProblem(
        T_c_w=T_noisy,
        xyz_w=X + rng.normal(scale=0.05, size=X.shape),
        pose_fixed=np.arange(K) < 2,
        point_fixed=np.zeros(M, bool),
        obs_pose=np.array(pose, np.int64),
        obs_point=np.array(point, np.int64),
        uv_px=np.array(uv),
        u_right_px=np.array(ur),
        level=np.zeros(E, np.int64),
        intrinsics=np.tile([fx, fy, cx, cy], (K, 1)),
        bf=np.full(K, bf if stereo else 0.0),
        scale_factor=1.2,
        iterations_first=5,
        iterations_second=10,
        robust=True,
    )


@pytest.mark.parametrize("stereo", [False, True])
def test_bundle_adjust_through_the_dense_step_is_the_former_solve(
    stereo: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    problem = _bundle_problem(7, stereo)
    got = bundle.bundle_adjust(problem, LMSettings())
    monkeypatch.setattr(bundle, "ba_solve_dense", _former_step)
    want = bundle.bundle_adjust(problem, LMSettings())
    assert got.iterations == want.iterations > 0
    assert np.array_equal(got.T_c_w, want.T_c_w)
    assert np.array_equal(got.xyz_w, want.xyz_w)
    assert np.array_equal(got.outlier, want.outlier)
    assert not np.array_equal(got.T_c_w, problem.T_c_w)  # the solver moved the free poses
