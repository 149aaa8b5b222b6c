"""Sim(3): similarity transforms x -> s R x + t (ORB-SLAM / g2o convention), stored [[s R, t], [0, 1]].

``S_a_b`` maps frame-b points into frame a with a scale change; ``S_a_b @ S_b_c == S_a_c``. Tangent vectors
are xi = [omega, v, lambda] with lambda = log s. The exponential is the true group exponential of the 4x4
generator [[hat(omega) + lambda I, v], [0, 0]]: s = e^lambda, R = exp(omega), t = W v with
W = integral_0^1 e^(lambda tau) exp(tau hat(omega)) d tau = A I + B hat(omega) + C hat(omega)^2.

GTSAM's Similarity3 is s (R x + t) instead; convert at that boundary (t_gtsam = t / s).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from slamkit.geometry._checks import F64, as_matrix, as_points
from slamkit.geometry.se3 import ORTHONORMAL_TOL, check_rotation
from slamkit.geometry.so3 import hat, so3_exp, so3_log

__all__ = ["Sim3"]

# Below this rotation angle (rad) B and C are evaluated from their series in theta^2 (the closed forms
# divide by theta^2 and lose ~eps/theta^2 relative precision: 1e-12 at this threshold).
_SMALL_THETA = 1e-2
# |lambda| up to this uses the power series of the moments; beyond it, their (then stable) recursion.
_SERIES_LAMBDA = 2.0


def _moments(lam: float, n_max: int) -> list[float]:
    """M_n = integral_0^1 tau^n e^(lam tau) d tau for n = 0..n_max, accurate for any lam."""
    if abs(lam) <= _SERIES_LAMBDA:
        # sum_k lam^k / (k! (n + k + 1)); 40 terms: 2^40/40! < 1e-36.
        out = []
        for n in range(n_max + 1):
            term, total = 1.0, 0.0
            for k in range(40):
                total += term / (n + k + 1)
                term *= lam / (k + 1)
            out.append(total)
        return out
    # M_n = (e^lam - n M_{n-1}) / lam: errors shrink by n / |lam| per step, fine for |lam| > 2 and n <= 8.
    e = math.exp(lam)
    out = [math.expm1(lam) / lam]
    for n in range(1, n_max + 1):
        out.append((e - n * out[-1]) / lam)
    return out


def _w_coefficients(theta: float, lam: float) -> tuple[float, float, float]:
    """(A, B, C) with A = int e^(l t), B = int e^(l t) sin(th t)/th, C = int e^(l t)(1 - cos(th t))/th^2."""
    A = math.expm1(lam) / lam if lam != 0.0 else 1.0
    if theta < _SMALL_THETA:
        # sin(th t)/th = sum_j (-1)^j th^2j t^(2j+1)/(2j+1)!, (1 - cos(th t))/th^2 = sum_j (-1)^j th^2j
        # t^(2j+2)/(2j+2)!; four terms leave < th^8/9! ~ 3e-22.
        M = _moments(lam, 8)
        t2 = theta * theta
        B = sum((-t2) ** j * M[2 * j + 1] / math.factorial(2 * j + 1) for j in range(4))
        C = sum((-t2) ** j * M[2 * j + 2] / math.factorial(2 * j + 2) for j in range(4))
        return A, B, C
    e = math.exp(lam)
    den = lam * lam + theta * theta
    sin_int = (e * (lam * math.sin(theta) - theta * math.cos(theta)) + theta) / den  # int e^(l t) sin(th t)
    cos_int = (e * (lam * math.cos(theta) + theta * math.sin(theta)) - lam) / den  # int e^(l t) cos(th t)
    return A, sin_int / theta, (A - cos_int) / (theta * theta)


def _w_matrix(omega: F64, lam: float) -> F64:
    A, B, C = _w_coefficients(float(np.linalg.norm(omega)), lam)
    W = hat(omega)
    out: F64 = A * np.eye(3) + B * W + C * (W @ W)
    return out


@dataclass(frozen=True, eq=False)
class Sim3:
    """Similarity transform x -> s R x + t.

    s: float scale (> 0); R: (3, 3) float64 rotation; t: (3,) float64 translation (m), stored read-only.
    Equality is identity; compare values with ``allclose``.
    """

    s: float
    R: F64
    t: F64

    def __post_init__(self) -> None:
        s = float(self.s)
        if not (math.isfinite(s) and s > 0.0):
            raise ValueError(f"Sim3.s: expected a positive finite scale, got {self.s!r}")
        R = np.array(as_matrix(self.R, (3, 3), "Sim3.R"))
        t = np.array(as_matrix(self.t, (3,), "Sim3.t"))
        check_rotation(R, "Sim3.R")
        R.setflags(write=False)
        t.setflags(write=False)
        object.__setattr__(self, "s", s)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)

    @classmethod
    def identity(cls) -> Sim3:
        """The identity (s = 1, R = I, t = 0)."""
        return cls(1.0, np.eye(3), np.zeros(3))

    @classmethod
    def from_matrix(cls, S: F64) -> Sim3:
        """S: (4, 4) [[s R, t], [0, 1]] -> Sim3 with s = cbrt(det(s R)).

        Raises ValueError when the 3x3 block is not a positive scale times a rotation (e.g. a reflection,
        shear or anisotropic scale) or the last row is not [0, 0, 0, 1].
        """
        M = as_matrix(S, (4, 4), "S")
        if not np.allclose(M[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
            raise ValueError(f"S: expected last row [0, 0, 0, 1], got {M[3].tolist()}")
        det = float(np.linalg.det(M[:3, :3]))
        if not det > 0.0:
            raise ValueError(f"S: the 3x3 block must be s R with s > 0 and R a rotation; its det is {det:.6g}")
        s = float(np.cbrt(det))
        R = M[:3, :3] / s
        err = float(np.abs(R @ R.T - np.eye(3)).max())
        if err > ORTHONORMAL_TOL:
            raise ValueError(
                f"S: the 3x3 block is not a similarity s R (after dividing by s = {s:.6g}, max |R R^T - I| = {err:.3g})"
            )
        return cls(s, R, M[:3, 3])

    @classmethod
    def from_se3(cls, T: F64, s: float = 1.0) -> Sim3:
        """T: (4, 4) rigid [[R, t], [0, 1]] -> Sim3(s, R, t), i.e. x -> s R x + t (t is kept as is)."""
        M = as_matrix(T, (4, 4), "T")
        if not np.allclose(M[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
            raise ValueError(f"T: expected last row [0, 0, 0, 1], got {M[3].tolist()}")
        return cls(s, M[:3, :3], M[:3, 3])

    def to_se3(self) -> F64:
        """(4, 4) float64 rigid transform [[R, t / s], [0, 1]] (scale dropped, ORB-SLAM's Sim3 -> Tcw).

        For S_c_w this is the camera pose in the world rescaled by 1/s: the rotation is unchanged and the
        camera centre -R^T t / s (the point S maps to the origin) is preserved. It maps x to (s R x + t) / s,
        not to s R x + t.
        """
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = self.t / self.s
        return T

    def matrix(self) -> F64:
        """(4, 4) float64 [[s R, t], [0, 1]]."""
        S = np.eye(4)
        S[:3, :3] = self.s * self.R
        S[:3, 3] = self.t
        return S

    def inverse(self) -> Sim3:
        """The inverse x -> R^T (x - t) / s."""
        return Sim3(1.0 / self.s, self.R.T, -(self.R.T @ self.t) / self.s)

    def __matmul__(self, other: Any) -> Sim3:
        """Composition: (A @ B).act(x) == A.act(B.act(x))."""
        if not isinstance(other, Sim3):
            return NotImplemented
        return Sim3(self.s * other.s, self.R @ other.R, self.s * (self.R @ other.t) + self.t)

    def act(self, xyz: F64) -> F64:
        """xyz: (N, 3) or (3,) points -> s R x + t of the same shape, float64."""
        pts, single = as_points(xyz, 3, "xyz")
        out = self.s * (pts @ self.R.T) + self.t
        return out[0] if single else out

    @classmethod
    def exp(cls, xi: F64) -> Sim3:
        """xi: (7,) [omega (rad), v, lambda = log s] -> the group exponential (s = e^lambda, t = W v)."""
        x = as_matrix(xi, (7,), "xi")
        lam = float(x[6])
        return cls(math.exp(lam), so3_exp(x[:3]), _w_matrix(x[:3], lam) @ x[3:6])

    def log(self) -> F64:
        """(7,) [omega, v, lambda] with exp(log(S)) == S; |omega| <= pi."""
        omega = so3_log(self.R)
        lam = math.log(self.s)
        v = np.linalg.solve(_w_matrix(omega, lam), self.t)
        return np.concatenate([omega, v, [lam]])

    def allclose(self, other: Sim3, atol: float = 1e-9) -> bool:
        """True when scale, rotation and translation agree elementwise to ``atol``."""
        return bool(
            abs(self.s - other.s) <= atol
            and np.allclose(self.R, other.R, atol=atol)
            and np.allclose(self.t, other.t, atol=atol)
        )

    def __repr__(self) -> str:
        return f"Sim3(s={self.s!r}, R={self.R.tolist()}, t={self.t.tolist()})"
