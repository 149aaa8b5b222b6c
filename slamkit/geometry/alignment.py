"""Closed-form alignment of two 3D point sets: dst ~ s R src + t.

``umeyama_alignment`` is Umeyama 1991 (SVD of the cross-covariance; least-squares scale).
``horn_alignment`` is Horn 1987 (unit quaternion as the top eigenvector of a 4x4 matrix), as ORB-SLAM's
Sim3Solver uses, with Horn's symmetric scale s = sqrt(sum |dst_i - mean|^2 / sum |src_i - mean|^2).
Both give the same rotation (the least-squares optimum); on noisy data their scales differ slightly, since
Umeyama's minimises ||dst - (s R src + t)||^2 while Horn's symmetric one treats both sets alike.
On noise-free data both recover the transform exactly.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from slamkit.geometry._checks import F64, as_float_array
from slamkit.geometry.sim3 import Sim3

__all__ = ["horn_alignment", "umeyama_alignment"]

# Second singular value of the centred points below this fraction of the first: collinear.
_COLLINEAR_RTOL = 1e-9


def _prepare(src: Any, dst: Any) -> tuple[F64, F64, F64, F64]:
    """Check shapes/values and centre both sets: (src_c, dst_c, mean_src, mean_dst)."""
    a = as_float_array(src, "src")
    b = as_float_array(dst, "dst")
    for name, arr in (("src", a), ("dst", b)):
        if arr.ndim != 2 or arr.shape[1] != 3:
            raise ValueError(f"{name}: expected an array of shape (N, 3), got shape {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name}: contains NaN or inf")
    if a.shape[0] != b.shape[0]:
        raise ValueError(f"src and dst: expected the same number of points, got {a.shape[0]} and {b.shape[0]}")
    if a.shape[0] < 3:
        raise ValueError(f"alignment needs at least 3 point pairs, got {a.shape[0]}")
    mu_a, mu_b = a.mean(axis=0), b.mean(axis=0)
    a_c, b_c = a - mu_a, b - mu_b
    for name, arr in (("src", a_c), ("dst", b_c)):
        sv = np.linalg.svd(arr, compute_uv=False)
        if sv[0] == 0.0 or sv[1] <= _COLLINEAR_RTOL * sv[0]:
            raise ValueError(
                f"{name}: the points are degenerate (all equal or collinear); "
                f"a 3D alignment needs at least 3 non-collinear points"
            )
    return a_c, b_c, mu_a, mu_b


def umeyama_alignment(src: F64, dst: F64, with_scale: bool) -> Sim3:
    """src, dst: (N, 3) corresponding points, N >= 3 -> Sim3 minimising sum |dst - (s R src + t)|^2.

    s = 1 when ``with_scale`` is False. Raises ValueError for N < 3, mismatched shapes, NaN/inf, or
    degenerate (coincident or collinear) points.
    """
    a_c, b_c, mu_a, mu_b = _prepare(src, dst)
    n = a_c.shape[0]
    cov = b_c.T @ a_c / n  # Sigma_xy of Umeyama (dst x src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0  # best proper rotation, not a reflection
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / (np.sum(a_c * a_c) / n)) if with_scale else 1.0
    return Sim3(s, R, mu_b - s * (R @ mu_a))


def horn_alignment(src: F64, dst: F64, with_scale: bool) -> Sim3:
    """src, dst: (N, 3) corresponding points, N >= 3 -> Sim3 with dst ~ s R src + t by Horn's quaternion method.

    The rotation's quaternion is the eigenvector of Horn's symmetric 4x4 matrix N (built from
    M = sum src_c dst_c^T) with the largest eigenvalue; s = sqrt(sum |dst_c|^2 / sum |src_c|^2) (Horn 1987,
    symmetric scale) when ``with_scale``, else 1; t = mean(dst) - s R mean(src). Same errors as
    ``umeyama_alignment``.
    """
    a_c, b_c, mu_a, mu_b = _prepare(src, dst)
    M = a_c.T @ b_c  # M[i, j] = sum src_i dst_j
    (sxx, sxy, sxz), (syx, syy, syz), (szx, szy, szz) = M
    N = np.array(
        [
            [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
            [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
            [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
            [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
        ]
    )
    _, vecs = np.linalg.eigh(N)
    w, x, y, z = vecs[:, -1]  # eigh sorts ascending
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    s = float(np.sqrt(np.sum(b_c * b_c) / np.sum(a_c * a_c))) if with_scale else 1.0
    return Sim3(s, R, mu_b - s * (R @ mu_a))
