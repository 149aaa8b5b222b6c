"""Relative Sim3 from matched points (ORB-SLAM Optimizer::OptimizeSim3, paper eq. 10-11) with a 7x7 LM.

The state is S_12 (x' = s R x + t, camera 2 -> camera 1), updated by left perturbation
S <- exp(delta) S, delta = [omega, v, lambda] (g2o's VertexSim3Expmap; with fix_scale lambda stays 0).
Each match contributes two reprojection errors (both Huber with delta = sqrt(chi2), information 1/sigma^2
of its level): e1 = pi_1(S_12 X2) - uv1 and e2 = pi_2(S_12^-1 X1) - uv2, pi_k the pinhole or Kannala-Brandt model of
keyframe k's camera (the problem's camera_model1/2; ORB-SLAM3 VertexSim3Expmap pCamera1/pCamera2).

Jacobians (first order in delta): d(S X2)/d delta = [-hat(p1), I, p1] with p1 = S X2; and since
(exp(delta) S)^-1 X1 = S^-1 exp(-delta) X1, d(S^-1 X1)/d delta = -(R^T / s) [-hat(X1), I, X1].

ORB-SLAM's schedule: ``iterations_first`` iterations, then the matches whose error in either direction
exceeds chi2 are removed; ``iterations_second`` more (ORB-SLAM runs 10 if it removed any, else 5).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slamkit.geometry.so3 import hat
from slamkit.optim.kannala_brandt import kb_project_many
from slamkit.problems import Sim3Problem, Sim3Result
from slamkit_scipy.lie import sim3_exp_batch, sim3_inverse_batch, sim3_split
from slamkit_scipy.lm import LMSettings, levenberg_marquardt
from slamkit_scipy.robust import huber_cost, huber_weight, inv_sigma2

F64 = NDArray[np.float64]


@dataclass
class _Matches:
    X1: F64  # (N, 3) points of keyframe 1 in camera 1
    X2: F64  # (N, 3) points of keyframe 2 in camera 2
    uv1: F64
    uv2: F64
    info1: F64
    info2: F64
    K1: F64  # (4,) fx fy cx cy
    K2: F64
    kb1: F64 | None = None  # (8,) fx fy cx cy k1..k4 of a Kannala-Brandt keyframe-1 camera; None: pinhole
    kb2: F64 | None = None

    def subset(self, keep: NDArray[np.bool_]) -> _Matches:
        return _Matches(
            self.X1[keep],
            self.X2[keep],
            self.uv1[keep],
            self.uv2[keep],
            self.info1[keep],
            self.info2[keep],
            self.K1,
            self.K2,
            self.kb1,
            self.kb2,
        )


def _project(p: F64, K: F64, kb: F64 | None = None) -> tuple[F64, F64]:
    """p: (N, 3) camera points -> (N, 2) px and (N, 2, 3) d pixel / d p, through the pinhole K (4,) or, when ``kb``
    (8,) is given, the Kannala-Brandt model (slamkit/optim/kannala_brandt.py; ORB-SLAM3 pCamera->project and
    projectJac for a fisheye keyframe)."""
    if kb is not None:
        uv_kb, A_kb = kb_project_many(np.ascontiguousarray(p, dtype=np.float64), kb)
        return uv_kb, A_kb
    fx, fy, cx, cy = K
    iz = 1.0 / p[:, 2]
    uv = np.column_stack([fx * p[:, 0] * iz + cx, fy * p[:, 1] * iz + cy])
    A = np.zeros((p.shape[0], 2, 3))
    A[:, 0, 0] = fx * iz
    A[:, 0, 2] = -fx * p[:, 0] * iz * iz
    A[:, 1, 1] = fy * iz
    A[:, 1, 2] = -fy * p[:, 1] * iz * iz
    return uv, A


def _transform(S: F64, X: F64) -> F64:
    out: F64 = X @ S[:3, :3].T + S[:3, 3]
    return out


def match_chi2(S: F64, m: _Matches) -> tuple[F64, F64, F64, F64]:
    """(N,) chi2 of directions 1 and 2 and (N,) depths of S X2 in camera 1 and S^-1 X1 in camera 2."""
    Sinv = sim3_inverse_batch(S[None])[0]
    p1 = _transform(S, m.X2)
    p2 = _transform(Sinv, m.X1)
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = _project(p1, m.K1, m.kb1)[0] - m.uv1
        r2 = _project(p2, m.K2, m.kb2)[0] - m.uv2
    return m.info1 * np.sum(r1 * r1, 1), m.info2 * np.sum(r2 * r2, 1), p1[:, 2], p2[:, 2]


def _cost(S: F64, m: _Matches, delta: float) -> float:
    c1, c2, _, _ = match_chi2(S, m)
    return float(np.sum(huber_cost(c1, delta)) + np.sum(huber_cost(c2, delta)))


def linearize_sim3(S: F64, *, m: _Matches, delta: float, dof: int) -> tuple[tuple[F64, F64], F64, float, float]:
    """At S_12 (4, 4): ((H, g), g, cost, max diag H) over both directions of every match (dof 7, or 6 with
    the scale fixed); IRLS Huber weights, so d cost / d delta = 2 g."""
    s, R, _ = sim3_split(S[None])
    Sinv = sim3_inverse_batch(S[None])[0]
    p1 = _transform(S, m.X2)
    p2 = _transform(Sinv, m.X1)
    uv1, A1 = _project(p1, m.K1, m.kb1)
    uv2, A2 = _project(p2, m.K2, m.kb2)
    r1 = uv1 - m.uv1
    r2 = uv2 - m.uv2
    c1 = m.info1 * np.sum(r1 * r1, 1)
    c2 = m.info2 * np.sum(r2 * r2, 1)
    n = p1.shape[0]
    G1 = np.zeros((n, 3, 7))
    G1[:, :, :3] = -hat(p1)
    G1[:, :, 3:6] = np.eye(3)
    G1[:, :, 6] = p1
    G2 = np.zeros((n, 3, 7))
    G2[:, :, :3] = -hat(m.X1)
    G2[:, :, 3:6] = np.eye(3)
    G2[:, :, 6] = m.X1
    G2 = -(R[0].T / s[0]) @ G2
    J1 = (A1 @ G1)[:, :, :dof]
    J2 = (A2 @ G2)[:, :, :dof]
    w1 = m.info1 * huber_weight(c1, delta)
    w2 = m.info2 * huber_weight(c2, delta)
    H = np.einsum("nki,n,nkj->ij", J1, w1, J1) + np.einsum("nki,n,nkj->ij", J2, w2, J2)
    g = np.einsum("nki,n,nk->i", J1, w1, r1) + np.einsum("nki,n,nk->i", J2, w2, r2)
    f = float(np.sum(huber_cost(c1, delta)) + np.sum(huber_cost(c2, delta)))
    return (H, g), g, f, float(np.max(np.diag(H)))


def _solve(system: tuple[F64, F64], lam: float) -> F64:
    H, g = system
    try:
        out: F64 = np.asarray(np.linalg.solve(H + lam * np.eye(H.shape[0]), -g), dtype=np.float64)
    except np.linalg.LinAlgError:
        return np.full(H.shape[0], np.nan)
    return out


def retract_sim3(S: F64, h: F64) -> F64:
    """S (4, 4) <- exp(h) S; h has 7 entries, or 6 (scale fixed: lambda = 0)."""
    xi = np.zeros(7)
    xi[: h.size] = h
    out: F64 = sim3_exp_batch(xi[None])[0] @ S
    return out


def _cost_at(S: F64, *, m: _Matches, delta: float) -> float:
    return _cost(S, m, delta)


def _run(S: F64, m: _Matches, delta: float, dof: int, iterations: int, settings: LMSettings) -> tuple[F64, int]:
    out = levenberg_marquardt(
        S,
        functools.partial(linearize_sim3, m=m, delta=delta, dof=dof),
        _solve,
        retract_sim3,
        functools.partial(_cost_at, m=m, delta=delta),
        iterations,
        settings,
    )
    return out.x, out.iterations


def _kb(intrinsics: F64, distortion: F64 | None) -> F64 | None:
    """(8,) fx fy cx cy k1..k4 of a Kannala-Brandt keyframe camera; None for a pinhole one (no distortion)."""
    if distortion is None:
        return None
    return np.concatenate([np.asarray(intrinsics, np.float64), np.asarray(distortion, np.float64)])


def optimize_sim3(problem: Sim3Problem, settings: LMSettings) -> Sim3Result:
    """Solve a validated Sim3Problem (module docstring)."""
    m_all = _Matches(
        np.asarray(problem.xyz1_c1, dtype=np.float64),
        np.asarray(problem.xyz2_c2, dtype=np.float64),
        np.asarray(problem.uv1_px, dtype=np.float64),
        np.asarray(problem.uv2_px, dtype=np.float64),
        inv_sigma2(np.asarray(problem.level1), problem.scale_factor),
        inv_sigma2(np.asarray(problem.level2), problem.scale_factor),
        np.asarray(problem.intrinsics1, dtype=np.float64),
        np.asarray(problem.intrinsics2, dtype=np.float64),
        _kb(problem.intrinsics1, problem.distortion1),
        _kb(problem.intrinsics2, problem.distortion2),
    )
    delta = float(np.sqrt(problem.chi2))
    dof = 6 if problem.fix_scale else 7

    S0 = np.array(problem.S_12_init, dtype=np.float64)
    n_all = m_all.X1.shape[0]
    cost_initial = _cost(S0, m_all, delta)
    S, iterations = _run(S0, m_all, delta, dof, problem.iterations_first, settings)
    c1, c2, z1, z2 = match_chi2(S, m_all)
    inlier = (c1 <= problem.chi2) & (c2 <= problem.chi2) & (z1 > 0.0) & (z2 > 0.0)
    if problem.iterations_second > 0 and np.any(inlier):
        # ORB-SLAM: 10 more iterations if matches were removed, else 5.
        more = problem.iterations_second if not np.all(inlier) else max(1, problem.iterations_second // 2)
        S, more_done = _run(S, m_all.subset(inlier), delta, dof, more, settings)
        iterations += more_done
        c1, c2, z1, z2 = match_chi2(S, m_all)
        inlier &= (c1 <= problem.chi2) & (c2 <= problem.chi2) & (z1 > 0.0) & (z2 > 0.0)
    cost_final = _cost(S, m_all.subset(inlier), delta) if n_all else 0.0
    return Sim3Result(S_12=S, inliers=inlier, cost_initial=cost_initial, cost_final=cost_final, iterations=iterations)
