"""Batched SE3/Sim3 maps for the solvers, built on slamkit.geometry.so3's batched primitives.

slamkit.geometry's SE3/Sim3 classes hold one transform each; the pose graph needs log/exp of thousands of
Sim3 at once per iteration, so this module evaluates the same maps over (N, ...) arrays. Conventions are
slamkit's (docs/conventions.md): Sim3 acts as x' = s R x + t, stored [[s R, t], [0, 1]]; tangents are
SE3 [omega, v] and Sim3 [omega, v, lambda] with lambda = log s; updates are left perturbations
S <- exp(delta) S (g2o's VertexSE3Expmap / VertexSim3Expmap). The tests check every function against the
single-transform classes of slamkit.geometry.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from slamkit.geometry.so3 import _angle_coefficients, hat, so3_exp, so3_log

F64 = NDArray[np.float64]

# Rotation angles below this use the series of W's coefficients (the closed forms divide by theta^2).
_SMALL_THETA = 1e-2
# |lambda| up to this uses the power series of the moments int t^n e^(lambda t); beyond it the recursion.
_SERIES_LAMBDA = 2.0
_SERIES_TERMS = 40


def se3_exp_batch(xi: F64) -> F64:
    """xi: (N, 6) [omega (rad), v (m)] -> (N, 4, 4) exp(xi) = [[exp(omega), J_l(omega) v], [0, 1]].

    so3_exp(omega) = I + a W + b W^2 and so3_left_jacobian(omega) = I + b W + c W^2 share the angle, its coefficients,
    W = hat(omega) and W^2: computed once here (the same numpy calls on the same arrays as those two functions make,
    so the same bits; the pose-only solver's retraction calls it). The compiled retractions (the bundle adjustment's
    slamkit_scipy.kernels.ba_retract, tracking's pose optimization) use slamkit.geometry.se3_kernels.se3_exp_times,
    the same formulas in another evaluation order (equal to rounding; the tests compare them)."""
    w = np.asarray(xi, np.float64)[:, :3]
    a, b, c = _angle_coefficients(np.linalg.norm(w, axis=-1))
    W = hat(w)
    WW = W @ W
    out = np.zeros((xi.shape[0], 4, 4))
    out[:, :3, :3] = np.broadcast_to(np.eye(3), W.shape) + a[..., None, None] * W + b[..., None, None] * WW
    J = np.eye(3) + b[..., None, None] * W + c[..., None, None] * WW
    out[:, :3, 3] = np.einsum("nij,nj->ni", J, xi[:, 3:])
    out[:, 3, 3] = 1.0
    return out


def _moments(lam: F64, n_max: int) -> F64:
    """lam: (N,) -> (N, n_max + 1) M_n = int_0^1 t^n e^(lam t) dt, accurate for any lam."""
    small = np.abs(lam) <= _SERIES_LAMBDA
    ls = np.where(small, lam, 0.0)
    # Power series M_n = sum_k lam^k / (k! (n + k + 1)); 40 terms leave < 2^40 / 40! ~ 1e-36. As one product:
    # P[:, k] = lam^k / k! times the constant C[k, n] = 1 / (n + k + 1).
    k = np.arange(_SERIES_TERMS)
    P = np.cumprod(np.column_stack([np.ones_like(ls), ls[:, None] / (k[1:])[None, :]]), axis=1)
    C = 1.0 / (k[:, None] + np.arange(n_max + 1)[None, :] + 1.0)
    out: F64 = P @ C
    if not np.all(small):
        # M_n = (e^lam - n M_{n-1}) / lam: stable for |lam| > 2 (errors shrink by n / |lam| per step).
        big = ~small
        lb = lam[big]
        e = np.exp(lb)
        m = np.expm1(lb) / lb
        out[big, 0] = m
        for n in range(1, n_max + 1):
            m = (e - n * m) / lb
            out[big, n] = m
    return out


def _w_coefficients(theta: F64, lam: F64) -> tuple[F64, F64, F64]:
    """(N,) angles and log-scales -> A, B, C of W = A I + B hat(w) + C hat(w)^2 (see slamkit.geometry.sim3)."""
    lam_safe = np.where(lam == 0.0, 1.0, lam)
    A = np.where(lam == 0.0, 1.0, np.expm1(lam) / lam_safe)
    small = theta < _SMALL_THETA
    th = np.where(small, 1.0, theta)  # placeholder for the branch not taken (no 0/0)
    e = np.exp(lam)
    den = lam * lam + th * th
    sin_int = (e * (lam * np.sin(th) - th * np.cos(th)) + th) / den
    cos_int = (e * (lam * np.cos(th) + th * np.sin(th)) - lam) / den
    B = sin_int / th
    C = (A - cos_int) / (th * th)
    if np.any(small):
        M = _moments(lam[small], 8)
        t2 = theta[small] ** 2
        fact = [1.0, 1.0, 2.0, 6.0, 24.0, 120.0, 720.0, 5040.0, 40320.0]
        Bs = sum((-t2) ** j * M[:, 2 * j + 1] / fact[2 * j + 1] for j in range(4))
        Cs = sum((-t2) ** j * M[:, 2 * j + 2] / fact[2 * j + 2] for j in range(4))
        B = B.copy()
        C = C.copy()
        B[small] = Bs
        C[small] = Cs
    return A, B, C


def _w_matrix(omega: F64, lam: F64) -> F64:
    A, B, C = _w_coefficients(np.linalg.norm(omega, axis=1), lam)
    W = hat(omega)
    out: F64 = A[:, None, None] * np.eye(3) + B[:, None, None] * W + C[:, None, None] * (W @ W)
    return out


def sim3_exp_batch(xi: F64) -> F64:
    """xi: (N, 7) [omega, v, lambda] -> (N, 4, 4) [[s R, t], [0, 1]] with s = e^lambda, t = W v."""
    lam = xi[:, 6]
    out = np.zeros((xi.shape[0], 4, 4))
    out[:, :3, :3] = np.exp(lam)[:, None, None] * so3_exp(xi[:, :3])
    out[:, :3, 3] = np.einsum("nij,nj->ni", _w_matrix(xi[:, :3], lam), xi[:, 3:6])
    out[:, 3, 3] = 1.0
    return out


def sim3_split(S: F64) -> tuple[F64, F64, F64]:
    """S: (N, 4, 4) [[s R, t], [0, 1]] -> s (N,), R (N, 3, 3), t (N, 3); s = cbrt(det(s R))."""
    sR = S[:, :3, :3]
    s = np.cbrt(np.linalg.det(sR))
    return s, sR / s[:, None, None], S[:, :3, 3]


def sim3_log_batch(S: F64) -> F64:
    """S: (N, 4, 4) Sim3 matrices -> (N, 7) [omega, v, lambda] with exp(log(S)) == S, |omega| <= pi."""
    s, R, t = sim3_split(S)
    omega = so3_log(R)
    lam = np.log(s)
    v = np.linalg.solve(_w_matrix(omega, lam), t[:, :, None])[:, :, 0]
    return np.concatenate([omega, v, lam[:, None]], axis=1)


def sim3_inverse_batch(S: F64) -> F64:
    """S: (N, 4, 4) -> (N, 4, 4) inverses [[R^T / s, -R^T t / s], [0, 1]]."""
    s, R, t = sim3_split(S)
    out = np.zeros_like(S)
    Rt = np.swapaxes(R, 1, 2) / s[:, None, None]
    out[:, :3, :3] = Rt
    out[:, :3, 3] = -np.einsum("nij,nj->ni", Rt, t)
    out[:, 3, 3] = 1.0
    return out


def sim3_adjoint_batch(S: F64) -> F64:
    """S: (N, 4, 4) -> (N, 7, 7) Ad_S with S exp(xi) S^-1 = exp(Ad_S xi), xi = [omega, v, lambda].

    Ad = [[R, 0, 0], [hat(t) R, s R, -t], [0, 0, 1]] (from S xi^ S^-1 with xi^ = [[hat(w) + l I, v], [0, 0]]).
    """
    s, R, t = sim3_split(S)
    n = S.shape[0]
    Ad = np.zeros((n, 7, 7))
    Ad[:, :3, :3] = R
    Ad[:, 3:6, :3] = hat(t) @ R
    Ad[:, 3:6, 3:6] = s[:, None, None] * R
    Ad[:, 3:6, 6] = -t
    Ad[:, 6, 6] = 1.0
    return Ad


def sim3_ad_batch(xi: F64) -> F64:
    """xi: (N, 7) -> (N, 7, 7) ad_xi, the Lie bracket [xi, y] = ad_xi y of sim(3).

    ad = [[hat(w), 0, 0], [hat(v), hat(w) + l I, -v], [0, 0, 0]].
    """
    n = xi.shape[0]
    ad = np.zeros((n, 7, 7))
    W = hat(xi[:, :3])
    ad[:, :3, :3] = W
    ad[:, 3:6, :3] = hat(xi[:, 3:6])
    ad[:, 3:6, 3:6] = W + xi[:, 6, None, None] * np.eye(3)
    ad[:, 3:6, 6] = -xi[:, 3:6]
    return ad
