"""SO(3): skew matrices, exponential and logarithm maps, Jacobians, and quaternion conversions.

Rotation vectors ``phi`` are axis * angle in radians. Functions accept a single (3,) vector / (3, 3)
matrix or a batch with leading dimensions (..., 3) / (..., 3, 3) and return float64 of matching shape.
Quaternions are (x, y, z, w) (TUM order); they appear only at I/O boundaries (docs/conventions.md).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from slamkit.geometry._checks import F64, as_batch_matrix, as_float_array

__all__ = [
    "hat",
    "matrix_to_quat_xyzw",
    "quat_xyzw_to_matrix",
    "so3_exp",
    "so3_left_jacobian",
    "so3_left_jacobian_inv",
    "so3_log",
    "so3_right_jacobian",
    "so3_right_jacobian_inv",
    "vee",
]

# Below this angle (rad) the closed forms lose precision; their Taylor series are used instead.
_SMALL_ANGLE = 1e-4


def _as_vectors(value: Any, name: str) -> F64:
    arr = as_float_array(value, name)
    if arr.ndim < 1 or arr.shape[-1] != 3:
        raise ValueError(f"{name}: expected an array of shape (3,) or (..., 3), got shape {arr.shape}")
    return arr


def hat(v: F64) -> F64:
    """v: (..., 3) -> (..., 3, 3) skew-symmetric matrix with hat(a) @ b == cross(a, b)."""
    w = _as_vectors(v, "v")
    out = np.zeros((*w.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -w[..., 2], w[..., 1]
    out[..., 1, 0], out[..., 1, 2] = w[..., 2], -w[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -w[..., 1], w[..., 0]
    return out


def vee(M: F64) -> F64:
    """M: (..., 3, 3) skew-symmetric -> (..., 3); the inverse of ``hat`` (uses the antisymmetric part)."""
    A = as_batch_matrix(M, (3, 3), "M")
    return 0.5 * np.stack([A[..., 2, 1] - A[..., 1, 2], A[..., 0, 2] - A[..., 2, 0], A[..., 1, 0] - A[..., 0, 1]], -1)


def _angle_coefficients(theta: F64) -> tuple[F64, F64, F64]:
    """a = sin(t)/t, b = (1 - cos t)/t^2, c = (t - sin t)/t^3, with series for small t."""
    small = theta < _SMALL_ANGLE
    t = np.where(small, 1.0, theta)  # placeholder avoids 0/0 in the branch not taken
    t2 = theta * theta
    a = np.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, np.sin(t) / t)
    b = np.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - np.cos(t)) / (t * t))
    c = np.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, (t - np.sin(t)) / (t * t * t))
    return a, b, c


def so3_exp(phi: F64) -> F64:
    """phi: (..., 3) rotation vector, rad -> (..., 3, 3) rotation matrix (Rodrigues' formula)."""
    w = _as_vectors(phi, "phi")
    theta = np.linalg.norm(w, axis=-1)
    a, b, _ = _angle_coefficients(theta)
    W = hat(w)
    eye = np.broadcast_to(np.eye(3), W.shape)
    out: F64 = eye + a[..., None, None] * W + b[..., None, None] * (W @ W)
    return out


def so3_log(R: F64) -> F64:
    """R: (..., 3, 3) rotation matrix -> (..., 3) rotation vector with angle in [0, pi].

    The angle comes from atan2(|sin|, cos), accurate everywhere. Near 0 the axis is the antisymmetric
    part divided by sinc; beyond pi/2 (where sin loses precision as the angle nears pi) the axis is read
    from the symmetric part R + R^T = 2 cos I + 2 (1 - cos) n n^T, with its sign from the antisymmetric part.
    """
    M = as_batch_matrix(R, (3, 3), "R")
    batch = M.shape[:-2]
    M = M.reshape(-1, 3, 3)
    s_vec = vee(M)  # sin(theta) * n
    sin_t = np.linalg.norm(s_vec, axis=-1)
    cos_t = 0.5 * (np.trace(M, axis1=-2, axis2=-1) - 1.0)
    theta = np.arctan2(sin_t, cos_t)
    out = np.empty((M.shape[0], 3))

    near_zero = theta < _SMALL_ANGLE
    t2 = theta * theta
    out[near_zero] = s_vec[near_zero] * (1.0 + t2[near_zero] / 6.0 + 7.0 * t2[near_zero] ** 2 / 360.0)[:, None]

    mid = ~near_zero & (cos_t >= 0.0)
    out[mid] = s_vec[mid] * (theta[mid] / sin_t[mid])[:, None]

    large = ~near_zero & (cos_t < 0.0)
    if np.any(large):
        Ml = M[large]
        nnT = (0.5 * (Ml + np.swapaxes(Ml, -1, -2)) - cos_t[large][:, None, None] * np.eye(3)) / (1.0 - cos_t[large])[
            :, None, None
        ]
        diag = np.diagonal(nnT, axis1=-2, axis2=-1)
        col = np.argmax(diag, axis=-1)
        idx = np.arange(Ml.shape[0])
        n = nnT[idx, :, col] / np.sqrt(diag[idx, col])[:, None]
        sign = np.where(np.einsum("ij,ij->i", n, s_vec[large]) < 0.0, -1.0, 1.0)
        out[large] = n * (sign * theta[large])[:, None]
    return out.reshape(*batch, 3)


def so3_left_jacobian(phi: F64) -> F64:
    """phi: (..., 3) -> (..., 3, 3) left Jacobian J_l = I + b hat(phi) + c hat(phi)^2 (also SE3's V matrix)."""
    w = _as_vectors(phi, "phi")
    _, b, c = _angle_coefficients(np.linalg.norm(w, axis=-1))
    W = hat(w)
    out: F64 = np.eye(3) + b[..., None, None] * W + c[..., None, None] * (W @ W)
    return out


def so3_right_jacobian(phi: F64) -> F64:
    """phi: (..., 3) -> (..., 3, 3) right Jacobian J_r(phi) = J_l(-phi)."""
    return so3_left_jacobian(-_as_vectors(phi, "phi"))


def so3_left_jacobian_inv(phi: F64) -> F64:
    """phi: (..., 3) -> (..., 3, 3) inverse of the left Jacobian: I - hat/2 + e hat^2,
    e = 1/t^2 - (1 + cos t) / (2 t sin t) (series near 0). Singular at |phi| = 2 pi, not reached for
    angles in [0, pi]."""
    w = _as_vectors(phi, "phi")
    theta = np.linalg.norm(w, axis=-1)
    small = theta < _SMALL_ANGLE
    t = np.where(small, 1.0, theta)
    t2 = theta * theta
    e = np.where(
        small, 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0, 1.0 / (t * t) - (1.0 + np.cos(t)) / (2.0 * t * np.sin(t))
    )
    W = hat(w)
    out: F64 = np.eye(3) - 0.5 * W + e[..., None, None] * (W @ W)
    return out


def so3_right_jacobian_inv(phi: F64) -> F64:
    """phi: (..., 3) -> (..., 3, 3) inverse of the right Jacobian, J_r^-1(phi) = J_l^-1(-phi)."""
    return so3_left_jacobian_inv(-_as_vectors(phi, "phi"))


def quat_xyzw_to_matrix(q: F64) -> F64:
    """q: (4,) or (N, 4) quaternion (x, y, z, w), any non-zero norm -> (3, 3) or (N, 3, 3) rotation."""
    arr = as_float_array(q, "q")
    if arr.ndim not in (1, 2) or arr.shape[-1] != 4:
        raise ValueError(f"q: expected an array of shape (4,) or (N, 4), got shape {arr.shape}")
    norm = np.linalg.norm(arr, axis=-1, keepdims=True)
    if not np.all(np.isfinite(arr)) or np.any(norm < 1e-12):
        raise ValueError("q: expected finite quaternions with non-zero norm")
    x, y, z, w = np.moveaxis(arr / norm, -1, 0)
    R = np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )
    return R


def matrix_to_quat_xyzw(R: F64) -> F64:
    """R: (3, 3) or (N, 3, 3) rotation -> (4,) or (N, 4) unit quaternion (x, y, z, w) with w >= 0.

    Shepperd's method: the largest of 4w^2, 4x^2, 4y^2, 4z^2 (read from the trace and the diagonal) is
    computed by a square root and the others from off-diagonal sums, which keeps full precision.
    """
    M = as_batch_matrix(R, (3, 3), "R")
    if M.ndim not in (2, 3):
        raise ValueError(f"R: expected an array of shape (3, 3) or (N, 3, 3), got shape {M.shape}")
    single = M.ndim == 2
    M = M.reshape(-1, 3, 3)
    d0, d1, d2 = M[:, 0, 0], M[:, 1, 1], M[:, 2, 2]
    # 4 * (w^2, x^2, y^2, z^2)
    cand = np.stack([1 + d0 + d1 + d2, 1 + d0 - d1 - d2, 1 - d0 + d1 - d2, 1 - d0 - d1 + d2], -1)
    pick = np.argmax(cand, axis=-1)
    r = 0.5 * np.sqrt(np.maximum(cand[np.arange(M.shape[0]), pick], 1e-300))  # = |component| * ... / 2
    # 4 * (w x, w y, w z, x y, x z, y z) from off-diagonals
    wx, wy, wz = M[:, 2, 1] - M[:, 1, 2], M[:, 0, 2] - M[:, 2, 0], M[:, 1, 0] - M[:, 0, 1]
    xy, xz, yz = M[:, 0, 1] + M[:, 1, 0], M[:, 0, 2] + M[:, 2, 0], M[:, 1, 2] + M[:, 2, 1]
    q = np.empty((M.shape[0], 4))  # x, y, z, w
    rows = [
        np.stack([wx, wy, wz, 4 * r * r], -1),  # w largest: scale by 1/(4w), w = r
        np.stack([4 * r * r, xy, xz, wx], -1),  # x largest
        np.stack([xy, 4 * r * r, yz, wy], -1),  # y largest
        np.stack([xz, yz, 4 * r * r, wz], -1),  # z largest
    ]
    for i, row in enumerate(rows):
        sel = pick == i
        q[sel] = row[sel] / (4 * r[sel])[:, None]
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q[q[:, 3] < 0] *= -1.0
    return q[0] if single else q
