"""Nonlinear refinement of an essential matrix on its 5-dof manifold (Sampson error in pixels).

Not part of ORB-SLAM, which decomposes the linear 8-point F directly and leaves refinement to the full
BA after initialization. The linear F has 7 dof and its projection onto the essential manifold loses
accuracy: at 1 px noise the motion is then degrees off, which fails the 0.9 x inliers test of the
hypothesis check. Minimising the Sampson error over E = [t]x R restores the accuracy the data allow.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from slamkit.geometry.so3 import hat, so3_exp

F64 = NDArray[np.float64]

_FD_STEP = 1e-7  # finite-difference step on the 5 tangent parameters (rad / unit-sphere tangent)


def sampson_residuals_px(F21: F64, uv1: F64, uv2: F64) -> F64:
    """F21: (3, 3); uv1, uv2: (N, 2) px -> (N,) signed Sampson distances x2^T F x1 / |grad|, px."""
    l2 = uv1 @ F21[:, :2].T + F21[:, 2]  # F x1
    l1 = uv2 @ F21[:2, :] + F21[2, :]  # F^T x2
    num = l2[:, 0] * uv2[:, 0] + l2[:, 1] * uv2[:, 1] + l2[:, 2]
    den = np.sqrt(l2[:, 0] ** 2 + l2[:, 1] ** 2 + l1[:, 0] ** 2 + l1[:, 1] ** 2)
    out: F64 = num / np.maximum(den, 1e-300)
    return out


def _tangent_basis(t: F64) -> F64:
    """(3,) unit t -> (3, 2) orthonormal basis of the plane orthogonal to t."""
    a = np.eye(3)[int(np.argmin(np.abs(t)))]
    b1 = np.cross(t, a)
    b1 /= np.linalg.norm(b1)
    return np.stack([b1, np.cross(t, b1)], axis=1)


def _fundamental(R: F64, t: F64, K_inv: F64) -> F64:
    out: F64 = K_inv.T @ hat(t) @ R @ K_inv
    return out


def _retract(R: F64, t: F64, delta: F64, basis: F64 | None = None) -> tuple[F64, F64]:
    """Apply a 5-vector [omega (3), beta (2)]: R <- exp(omega) R, t <- normalise(t + B beta). basis: B =
    ``_tangent_basis(t)`` when the caller has it (a pure function of t: the same B either way)."""
    B = _tangent_basis(t) if basis is None else basis
    t_new = t + B @ delta[3:]
    return so3_exp(delta[:3]) @ R, t_new / np.linalg.norm(t_new)


def refine_essential(R: F64, t: F64, K: F64, uv1: F64, uv2: F64, *, iterations: int = 10) -> tuple[F64, F64]:
    """Levenberg-Marquardt on E = [t]x R minimising the Sampson error of matches (N >= 5) in px.

    R: (3, 3), t: (3,) any motion consistent with E (the Sampson error cannot tell the 4 hypotheses
    apart); K: (3, 3); uv1, uv2: (N, 2) px. Returns the refined (R, t), |t| = 1.
    """
    K_inv: F64 = np.asarray(np.linalg.inv(K), dtype=np.float64)
    t = t / np.linalg.norm(t)
    r = sampson_residuals_px(_fundamental(R, t, K_inv), uv1, uv2)
    cost = float(r @ r)
    lam = 1e-3
    for _ in range(iterations):
        J = np.empty((r.size, 5))
        basis = _tangent_basis(t)  # the tangent plane at t, for the 5 differences and the trial steps
        for k in range(5):  # forward differences: 5 cheap vectorised evaluations
            step = np.zeros(5)
            step[k] = _FD_STEP
            Rk, tk = _retract(R, t, step, basis)
            J[:, k] = (sampson_residuals_px(_fundamental(Rk, tk, K_inv), uv1, uv2) - r) / _FD_STEP
        g = J.T @ r
        A = J.T @ J
        improved = False
        for _ in range(5):  # raise the damping until the step lowers the cost
            delta: F64 = np.asarray(np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-12), -g), dtype=np.float64)
            R_new, t_new = _retract(R, t, delta, basis)
            r_new = sampson_residuals_px(_fundamental(R_new, t_new, K_inv), uv1, uv2)
            cost_new = float(r_new @ r_new)
            if cost_new < cost:
                R, t, r = R_new, t_new, r_new
                improved = cost - cost_new > 1e-10 * cost
                cost = cost_new
                lam = max(lam / 10.0, 1e-9)
                break
            lam *= 10.0
        if not improved:
            break
    return R, t
