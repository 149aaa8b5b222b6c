"""SE(3): rigid transforms as an immutable float64 (R, t) pair, plus helpers for batches of 4x4 matrices.

``SE3(R, t)`` maps x -> R x + t; named after docs/conventions.md, ``T_a_b`` maps frame-b points to frame a
and ``T_a_b @ T_b_c == T_a_c``. Tangent vectors are xi = [omega, v] (rotation first, as GTSAM's Pose3),
with exp(xi) = [[exp(omega), J_l(omega) v], [0, 1]] (the true group exponential, J_l = SO3's left Jacobian).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from slamkit.geometry._checks import F64, as_batch_matrix, as_matrix, as_points
from slamkit.geometry.so3 import hat, so3_exp, so3_left_jacobian, so3_left_jacobian_inv, so3_log

__all__ = ["SE3", "invert_T", "orthonormalized_T", "transform_points"]

# A rotation whose R R^T differs from I by more than this is rejected (not a rotation, not roundoff).
# Loose enough for poses printed with ~7 significant digits (KITTI ground truth).
ORTHONORMAL_TOL = 1e-5


def check_rotation(R: F64, name: str) -> None:
    """ValueError unless R (3, 3) is orthonormal with det +1 to within ORTHONORMAL_TOL."""
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    if err > ORTHONORMAL_TOL or np.linalg.det(R) < 0:
        raise ValueError(
            f"{name}: expected a rotation matrix (R R^T = I, det = +1); "
            f"max |R R^T - I| = {err:.3g}, det = {np.linalg.det(R):.6g}"
        )


def nearest_rotation(M: F64) -> F64:
    """(3, 3) -> the closest rotation matrix in the Frobenius norm (SVD projection with det +1)."""
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    out: F64 = U @ D @ Vt
    return out


@dataclass(frozen=True, eq=False)
class SE3:
    """Rigid transform x -> R x + t.

    R: (3, 3) float64 rotation; t: (3,) float64 translation (m). Both are stored read-only.
    Equality is identity; compare values with ``allclose``.
    """

    R: F64
    t: F64

    def __post_init__(self) -> None:
        R = np.array(as_matrix(self.R, (3, 3), "SE3.R"))
        t = np.array(as_matrix(self.t, (3,), "SE3.t"))
        check_rotation(R, "SE3.R")
        R.setflags(write=False)
        t.setflags(write=False)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)

    @classmethod
    def identity(cls) -> SE3:
        """The identity transform."""
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_matrix(cls, T: F64, *, orthonormalize: bool = False) -> SE3:
        """T: (4, 4) homogeneous matrix with last row [0, 0, 0, 1]. With ``orthonormalize`` the rotation
        block is projected onto SO(3) first (for matrices read from text with few digits)."""
        M = as_matrix(T, (4, 4), "T")
        if not np.allclose(M[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
            raise ValueError(f"T: expected last row [0, 0, 0, 1], got {M[3].tolist()}")
        R = nearest_rotation(M[:3, :3]) if orthonormalize else M[:3, :3]
        return cls(R, M[:3, 3])

    def matrix(self) -> F64:
        """(4, 4) float64 homogeneous matrix [[R, t], [0, 1]]."""
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = self.t
        return T

    def inverse(self) -> SE3:
        """The inverse transform x -> R^T (x - t)."""
        return SE3(self.R.T, -self.R.T @ self.t)

    def __matmul__(self, other: Any) -> SE3:
        """Composition: (A @ B).act(x) == A.act(B.act(x))."""
        if not isinstance(other, SE3):
            return NotImplemented
        return SE3(self.R @ other.R, self.R @ other.t + self.t)

    def act(self, xyz: F64) -> F64:
        """xyz: (N, 3) or (3,) points (m) -> transformed points of the same shape, float64."""
        pts, single = as_points(xyz, 3, "xyz")
        out = pts @ self.R.T + self.t
        return out[0] if single else out

    @classmethod
    def exp(cls, xi: F64) -> SE3:
        """xi: (6,) tangent vector [omega (rad), v (m)] -> exp(xi) with t = J_l(omega) v."""
        x = as_matrix(xi, (6,), "xi")
        return cls(so3_exp(x[:3]), so3_left_jacobian(x[:3]) @ x[3:])

    def log(self) -> F64:
        """(6,) tangent vector [omega, v] with exp(log(T)) == T; |omega| <= pi."""
        omega = so3_log(self.R)
        return np.concatenate([omega, so3_left_jacobian_inv(omega) @ self.t])

    def adjoint(self) -> F64:
        """(6, 6) adjoint for xi = [omega, v]: T exp(xi) T^-1 == exp(Ad_T xi); Ad = [[R, 0], [hat(t) R, R]]."""
        Ad = np.zeros((6, 6))
        Ad[:3, :3] = self.R
        Ad[3:, 3:] = self.R
        Ad[3:, :3] = hat(self.t) @ self.R
        return Ad

    def allclose(self, other: SE3, atol: float = 1e-9) -> bool:
        """True when rotation and translation agree elementwise to ``atol``."""
        return bool(np.allclose(self.R, other.R, atol=atol) and np.allclose(self.t, other.t, atol=atol))

    def __repr__(self) -> str:
        return f"SE3(R={self.R.tolist()}, t={self.t.tolist()})"


def orthonormalized_T(T: F64) -> F64:
    """T: (4, 4) rigid transform -> the same with its rotation block projected onto SO(3) (``nearest_rotation``) and
    last row [0, 0, 0, 1]: ``SE3.from_matrix(T, orthonormalize=True).matrix()`` without building and checking an SE3
    (per frame in tracking, where products of poses drift off SO(3) by roundoff only)."""
    M = as_matrix(T, (4, 4), "T")
    out = np.eye(4)
    out[:3, :3] = nearest_rotation(M[:3, :3])
    out[:3, 3] = M[:3, 3]
    return out


def invert_T(T: F64) -> F64:
    """T: (..., 4, 4) rigid transforms -> (..., 4, 4) inverses [[R^T, -R^T t], [0, 1]] (no general inverse)."""
    M = as_batch_matrix(T, (4, 4), "T")
    R = M[..., :3, :3]
    t = M[..., :3, 3]
    Rt = np.swapaxes(R, -1, -2)
    out = np.zeros_like(M)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def transform_points(T: F64, xyz: F64) -> F64:
    """T: (4, 4) transform T_a_b; xyz: (N, 3) or (3,) points in frame b -> same shape in frame a."""
    M = as_matrix(T, (4, 4), "T")
    pts, single = as_points(xyz, 3, "xyz")
    out = pts @ M[:3, :3].T + M[:3, 3]
    return out[0] if single else out
