"""Compiled scoring of the RANSAC hypotheses (ransac.py's ``score_homographies`` / ``score_fundamentals``).

One pass over the (B hypotheses, M matches) pairs, GIL-free, in place of numpy's (B, M, 3) temporaries. Each entry is
computed with the operations of the numpy expressions it replaces, in their order (no fused multiply-add: numba
compiles without fastmath), so the per-entry contributions are bit for bit numpy's; the sum over the matches stays
numpy's (``ransac.py``), whose pairwise summation order these loops do not reproduce.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
B8 = NDArray[np.bool_]


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _transfer_sq(H: F64, b: int, x: float, y: float, xt: float, yt: float) -> float:  # pragma: no cover - numba
    """Squared px distance between (xt, yt) and H[b] (x, y, 1) dehomogenised (ransac._transfer_sq's arithmetic)."""
    p0 = x * H[b, 0, 0] + y * H[b, 0, 1] + H[b, 0, 2]
    p1 = x * H[b, 1, 0] + y * H[b, 1, 1] + H[b, 1, 2]
    p2 = x * H[b, 2, 0] + y * H[b, 2, 1] + H[b, 2, 2]
    d0 = p0 / p2 - xt
    d1 = p1 / p2 - yt
    return d0 * d0 + d1 * d1


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _scored_pair(chi_a: float, chi_b: float, T: float, gamma: float) -> tuple[float, bool]:  # pragma: no cover
    """ORB-SLAM's two-image score of one match: rho(chi) = gamma - chi where chi <= T, else 0 (NaN fails), summed
    over both images; and whether both pass."""
    ok_a = chi_a <= T
    ok_b = chi_b <= T
    s_a = gamma - chi_a if ok_a else 0.0
    s_b = gamma - chi_b if ok_b else 0.0
    return s_a + s_b, ok_a and ok_b


@numba.njit(cache=True, nogil=True, error_model="numpy")
def homography_contributions(
    H21: F64, H12: F64, uv1: F64, uv2: F64, inv_s2: float, T_H: float, gamma: float
) -> tuple[F64, B8]:  # pragma: no cover - numba
    """H21, H12: (B, 3, 3) (H12 ~ adj(H21)); uv1, uv2: (M, 2) px -> ((B, M) rho(chi_cur) + rho(chi_ref), (B, M)
    inlier mask), as ORB-SLAM's CheckHomography: rho(chi2) = gamma - chi2 where chi2 <= T_H, else 0 (NaN fails)."""
    n_b, n_m = H21.shape[0], uv1.shape[0]
    s = np.empty((n_b, n_m))
    ok = np.empty((n_b, n_m), np.bool_)
    for b in range(n_b):
        for m in range(n_m):
            x1, y1, x2, y2 = uv1[m, 0], uv1[m, 1], uv2[m, 0], uv2[m, 1]
            chi_cur = _transfer_sq(H21, b, x1, y1, x2, y2) * inv_s2
            chi_ref = _transfer_sq(H12, b, x2, y2, x1, y1) * inv_s2
            s[b, m], ok[b, m] = _scored_pair(chi_cur, chi_ref, T_H, gamma)
    return s, ok


@numba.njit(cache=True, nogil=True, error_model="numpy")
def fundamental_contributions(
    F21: F64, uv1: F64, uv2: F64, inv_s2: float, T_F: float, gamma: float
) -> tuple[F64, B8]:  # pragma: no cover - numba
    """F21: (B, 3, 3); uv1, uv2: (M, 2) px -> ((B, M) rho(chi1) + rho(chi2), (B, M) inlier mask), as ORB-SLAM's
    CheckFundamental: squared point-to-epipolar-line distances in both images (in sigma^2), tested against T_F and
    scored with gamma."""
    n_b, n_m = F21.shape[0], uv1.shape[0]
    s = np.empty((n_b, n_m))
    ok = np.empty((n_b, n_m), np.bool_)
    for b in range(n_b):
        for m in range(n_m):
            u1, v1, u2, v2 = uv1[m, 0], uv1[m, 1], uv2[m, 0], uv2[m, 1]
            # epipolar line of x1 in image 2 (F x1) and of x2 in image 1 (F^T x2)
            a2 = u1 * F21[b, 0, 0] + v1 * F21[b, 0, 1] + F21[b, 0, 2]
            b2 = u1 * F21[b, 1, 0] + v1 * F21[b, 1, 1] + F21[b, 1, 2]
            c2 = u1 * F21[b, 2, 0] + v1 * F21[b, 2, 1] + F21[b, 2, 2]
            a1 = u2 * F21[b, 0, 0] + v2 * F21[b, 1, 0] + F21[b, 2, 0]
            b1 = u2 * F21[b, 0, 1] + v2 * F21[b, 1, 1] + F21[b, 2, 1]
            c1 = u2 * F21[b, 0, 2] + v2 * F21[b, 1, 2] + F21[b, 2, 2]
            num2 = a2 * u2 + b2 * v2 + c2
            num1 = a1 * u1 + b1 * v1 + c1
            chi2 = num2 * num2 / (a2 * a2 + b2 * b2) * inv_s2
            chi1 = num1 * num1 / (a1 * a1 + b1 * b1) * inv_s2
            s[b, m], ok[b, m] = _scored_pair(chi1, chi2, T_F, gamma)
    return s, ok
