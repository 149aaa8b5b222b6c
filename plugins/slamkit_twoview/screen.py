"""Compiled screening of a motion hypothesis' points (reconstruct.py's ``check_motion_screened``).

ORB-SLAM's CheckRT triangulates every model inlier under each motion hypothesis (8 for H, 4 for F) and grades it. The
exact path (reconstruct.py's ``check_motion``) solves each point's 4x4 DLT system by LAPACK's SVD, whose per-matrix
cost dominates an initialisation attempt. Here each point is solved instead by a one-sided Jacobi SVD (Hestenes) in
one GIL-free pass, and graded with a margin: a point whose every test (finite, depth sign in both cameras, near-parallel
rays, reprojection error in both images) passes or fails by more than a bound on the difference between this solution
and LAPACK's is decided here; any other point is flagged ``unsure`` and the caller decides it by the exact path. The
bound is conservative (a thousand times a first-order estimate of both solutions' error), so a decision made here is
the exact path's; the tests in tests/unit/plugins/test_twoview_screen.py compare the two on recorded and synthetic data.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
B8 = NDArray[np.bool_]

#: the machine epsilon of float64
_EPS = 2.220446049250313e-16
#: safety factor on the first-order error estimate of a solution (both solutions' errors, and the derived tests')
_SAFETY = 1e3
#: a point whose solution's relative error estimate is above this is left to the exact path
_MAX_REL_ERR = 1e-8
#: Jacobi sweeps at most (a 4x4 system converges in 4-6)
_MAX_SWEEPS = 30


@numba.njit(cache=True, nogil=True, inline="always")
def _null_vector_4x4(A: F64, out: F64) -> tuple[float, float]:  # pragma: no cover - numba
    """A: (4, 4) -> out (4,) the unit right singular vector of A's smallest singular value (one-sided Jacobi on A's
    columns, Hestenes 1958); returns (largest singular value, gap between the two smallest); gap 0: undecided."""
    U = A.copy()
    V = np.eye(4)
    for _ in range(_MAX_SWEEPS):
        rotated = False
        for p in range(3):
            for q in range(p + 1, 4):
                alpha = 0.0
                beta = 0.0
                gamma = 0.0
                for i in range(4):
                    alpha += U[i, p] * U[i, p]
                    beta += U[i, q] * U[i, q]
                    gamma += U[i, p] * U[i, q]
                if gamma == 0.0 or abs(gamma) <= _EPS * math.sqrt(alpha * beta):
                    continue
                rotated = True
                zeta = (beta - alpha) / (2.0 * gamma)
                t = (1.0 if zeta >= 0.0 else -1.0) / (abs(zeta) + math.sqrt(1.0 + zeta * zeta))
                c = 1.0 / math.sqrt(1.0 + t * t)
                s = c * t
                for i in range(4):
                    up, uq = U[i, p], U[i, q]
                    U[i, p] = c * up - s * uq
                    U[i, q] = s * up + c * uq
                    vp, vq = V[i, p], V[i, q]
                    V[i, p] = c * vp - s * vq
                    V[i, q] = s * vp + c * vq
        if not rotated:
            break
    sig = np.empty(4)
    for j in range(4):
        acc = 0.0
        for i in range(4):
            acc += U[i, j] * U[i, j]
        sig[j] = math.sqrt(acc)
    order = np.argsort(sig)
    k = order[0]
    nv = 0.0
    for i in range(4):
        nv += V[i, k] * V[i, k]
    nv = math.sqrt(nv)
    for i in range(4):
        out[i] = V[i, k] / nv
    return sig[order[3]], sig[order[1]] - sig[order[0]]


@numba.njit(cache=True, nogil=True, inline="always")
def _reprojection(P: F64, x: float, y: float, z: float, u: float, v: float) -> tuple[float, float]:  # pragma: no cover
    """P: (3, 4) K [R | t]; a point and its observed px -> (error px of its projection, or of its mirror through the
    camera centre when behind; the px scale of a unit change of the normalised image coordinates)."""
    h0 = P[0, 0] * x + P[0, 1] * y + P[0, 2] * z + P[0, 3]
    h1 = P[1, 0] * x + P[1, 1] * y + P[1, 2] * z + P[1, 3]
    h2 = P[2, 0] * x + P[2, 1] * y + P[2, 2] * z + P[2, 3]
    # the mirror image through the centre projects to the same px (h -> -h): ORB-SLAM's CheckRT ignores the sign
    du = h0 / h2 - u
    dv = h1 / h2 - v
    return math.sqrt(du * du + dv * dv), (abs(P[0, 0]) + abs(P[1, 1])) * (1.0 + (abs(h0) + abs(h1)) / abs(h2))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def screen_points(
    P1: F64,
    P2: F64,
    center2: F64,
    uv1: F64,
    uv2: F64,
    max_err_px: float,
    max_cos_parallax: float,
    at_infinity: float,
) -> tuple[F64, F64, F64, B8, B8, B8]:  # pragma: no cover - numba
    """Triangulate and grade N matches under one hypothesis, deciding only what a margin makes certain.

    P1, P2: (3, 4) projection matrices K [R | t] of the reference (world) and current cameras; center2: (3,) the
    current camera's centre in the reference frame; uv1, uv2: (N, 2) undistorted px; max_err_px, max_cos_parallax:
    CheckRT's thresholds; at_infinity: |X_4| at or below which a homogeneous solution is at infinity (NaN).
    Returns (xyz (N, 3) approximate points, NaN at infinity; parallax (N,) degrees; margin (N,) a bound (radians) on
    the parallax's difference from the exact path's; good (N,); near_parallel (N,); unsure (N,): the decision is left
    to the exact path, whose good / near_parallel the caller then uses).
    """
    n = uv1.shape[0]
    xyz = np.full((n, 3), np.nan)
    par = np.full(n, np.nan)
    par_margin = np.full(n, np.inf)
    good = np.zeros(n, np.bool_)
    near = np.zeros(n, np.bool_)
    unsure = np.zeros(n, np.bool_)
    A = np.empty((4, 4))
    X = np.empty(4)
    for m in range(n):
        u1, v1, u2, v2 = uv1[m, 0], uv1[m, 1], uv2[m, 0], uv2[m, 1]
        for j in range(4):
            A[0, j] = u1 * P1[2, j] - P1[0, j]
            A[1, j] = v1 * P1[2, j] - P1[1, j]
            A[2, j] = u2 * P2[2, j] - P2[0, j]
            A[3, j] = v2 * P2[2, j] - P2[1, j]
        finite = True
        for i in range(4):
            for j in range(4):
                if not math.isfinite(A[i, j]):
                    finite = False
        if not finite:
            unsure[m] = True
            continue
        s_max, gap = _null_vector_4x4(A, X)
        if not gap > 0.0:
            unsure[m] = True
            continue
        err_x = _SAFETY * _EPS * max(s_max, 1.0) / gap  # first-order bound on the null vector's error (angle)
        w = abs(X[3])
        if abs(w - at_infinity) <= err_x + at_infinity * 1e-6:
            unsure[m] = True
            continue
        if w <= at_infinity:  # at infinity for both solutions: NaN, not good
            continue
        rel = err_x / w  # relative error bound of the dehomogenised point
        if rel > _MAX_REL_ERR:
            unsure[m] = True
            continue
        margin = _SAFETY * rel + 1e-12
        x, y, z = X[0] / X[3], X[1] / X[3], X[2] / X[3]
        xyz[m, 0], xyz[m, 1], xyz[m, 2] = x, y, z
        # depths in both cameras, against the distance to each centre
        d1 = P1[2, 0] * x + P1[2, 1] * y + P1[2, 2] * z + P1[2, 3]  # K's last row is (0, 0, 1): the depth
        d2 = P2[2, 0] * x + P2[2, 1] * y + P2[2, 2] * z + P2[2, 3]
        r1 = math.sqrt(x * x + y * y + z * z)
        bx, by, bz = x - center2[0], y - center2[1], z - center2[2]
        r2 = math.sqrt(bx * bx + by * by + bz * bz)
        if abs(d1) <= margin * r1 or abs(d2) <= margin * r2 or r1 == 0.0 or r2 == 0.0:
            unsure[m] = True
            continue
        cos_par = (x * bx + y * by + z * bz) / (r1 * r2)
        if abs(cos_par - max_cos_parallax) <= margin:
            unsure[m] = True
            continue
        cx, cy, cz = y * bz - z * by, z * bx - x * bz, x * by - y * bx
        par_margin[m] = margin
        par[m] = math.degrees(math.atan2(math.sqrt(cx * cx + cy * cy + cz * cz), x * bx + y * by + z * bz))
        is_near = cos_par >= max_cos_parallax
        e1, scale1 = _reprojection(P1, x, y, z, u1, v1)
        e2, scale2 = _reprojection(P2, x, y, z, u2, v2)
        if abs(e1 - max_err_px) <= margin * scale1 or abs(e2 - max_err_px) <= margin * scale2:
            unsure[m] = True
            continue
        near[m] = is_near
        good[m] = ((d1 > 0.0 and d2 > 0.0) or is_near) and e1 <= max_err_px and e2 <= max_err_px
    return xyz, par, par_margin, good, near, unsure
