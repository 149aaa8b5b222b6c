"""Compiled tests of local mapping's triangulation (ORB-SLAM CreateNewMapPoints / SearchForTriangulation, VI-C) for a
pair of one-camera monocular keyframes with pinhole pipeline images: one pass over the candidate pairs instead of a
few dozen numpy round trips per neighbour (nogil: local mapping in a thread leaves the GIL to tracking).

Each kernel only decides (a bool per candidate); the point coordinates still come from the numpy DLT
(:func:`slamkit.geometry.twoview.triangulate_points`), so the map's numbers are those of the numpy path. The tests
evaluate the same formulas as the numpy code of ``slamkit.pipeline.local_mapping`` (operands in the same order;
numpy's matrix products may fuse a multiply-add where these do not, so a candidate lying within a rounding error of a
threshold could fall the other way: ``tests/unit/pipeline/test_triangulation_kernels.py`` compares both paths).
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
B = NDArray[np.bool_]


@numba.njit(cache=True, nogil=True)
def epipolar_candidates(
    uv1: F64,
    uv2: F64,
    F21: F64,
    sigma2: F64,
    chi2_epipolar: float,
    check_epipole: bool,
    epipole: F64,
    scale2: F64,
    epipole_min_dist2: float,
    stereo: B,
) -> B:  # pragma: no cover - compiled
    """uv1, uv2 (M, 2) px: a candidate pair's keypoints (undistorted pinhole pixels of kf1 / kf2); F21 (3, 3) with
    x2^T F21 x1 = 0; sigma2, scale2 (M,): kf2's level sigma^2 and scale at each candidate's keypoint; stereo (M,): either
    keypoint has a right coordinate. -> (M,) bool: the squared distance of uv2 to the epipolar line of uv1 is below
    chi2_epipolar sigma2 and, with ``check_epipole``, uv2 is not within sqrt(epipole_min_dist2 scale2) of the
    epipole (x, y) px ``epipole`` unless ``stereo`` (a NaN distance is never near)."""
    M = uv1.shape[0]
    ok = np.zeros(M, np.bool_)
    for i in range(M):
        u1 = uv1[i, 0]
        v1 = uv1[i, 1]
        l0 = u1 * F21[0, 0] + v1 * F21[0, 1] + F21[0, 2]
        l1 = u1 * F21[1, 0] + v1 * F21[1, 1] + F21[1, 2]
        l2 = u1 * F21[2, 0] + v1 * F21[2, 1] + F21[2, 2]
        num = l0 * uv2[i, 0] + l1 * uv2[i, 1] + l2
        den = l0**2 + l1**2
        dist2 = num**2 / (den if den > 1e-12 else 1e-12)
        good = dist2 < chi2_epipolar * sigma2[i]
        if good and check_epipole and not stereo[i]:
            dx = uv2[i, 0] - epipole[0]
            dy = uv2[i, 1] - epipole[1]
            if dx**2 + dy**2 < epipole_min_dist2 * scale2[i]:
                good = False
        ok[i] = good
    return ok


@numba.njit(cache=True, nogil=True)
def parallax_ok(uv1: F64, uv2: F64, Kinv1: F64, Kinv2: F64, R1: F64, R2: F64, min_parallax_cos: float) -> B:
    """uv1, uv2 (M, 2) px; Kinv (3, 3); R (3, 3) world -> camera rotations. -> (M,) bool: the cosine of the angle
    between the two keypoints' rays in the world (R^T K^-1 (u, v, 1)) is in (0, min_parallax_cos) (ORB-SLAM
    CreateNewMapPoints: cosParallaxRays < 0.9998 and > 0; NaN: False)."""  # pragma: no cover - compiled
    M = uv1.shape[0]
    ok = np.zeros(M, np.bool_)
    for i in range(M):
        r1 = _ray(uv1[i, 0], uv1[i, 1], Kinv1, R1)
        r2 = _ray(uv2[i, 0], uv2[i, 1], Kinv2, R2)
        dot = r1[0] * r2[0] + r1[1] * r2[1] + r1[2] * r2[2]
        n1 = np.sqrt(r1[0] * r1[0] + r1[1] * r1[1] + r1[2] * r1[2])
        n2 = np.sqrt(r2[0] * r2[0] + r2[1] * r2[1] + r2[2] * r2[2])
        c = dot / (n1 * n2)
        ok[i] = c > 0 and c < min_parallax_cos
    return ok


@numba.njit(cache=True, nogil=True, inline="always")
def _ray(u: float, v: float, Kinv: F64, R: F64) -> tuple[float, float, float]:  # pragma: no cover - compiled
    """R^T Kinv (u, v, 1): a keypoint's ray in the world frame (not normalised)."""
    x = u * Kinv[0, 0] + v * Kinv[0, 1] + Kinv[0, 2]
    y = u * Kinv[1, 0] + v * Kinv[1, 1] + Kinv[1, 2]
    z = u * Kinv[2, 0] + v * Kinv[2, 1] + Kinv[2, 2]
    return (
        x * R[0, 0] + y * R[1, 0] + z * R[2, 0],
        x * R[0, 1] + y * R[1, 1] + z * R[2, 1],
        x * R[0, 2] + y * R[1, 2] + z * R[2, 2],
    )


@numba.njit(cache=True, nogil=True)
def triangulated_ok(
    xyz: F64,
    uv1: F64,
    uv2: F64,
    T1: F64,
    T2: F64,
    intr1: F64,
    intr2: F64,
    gate1: F64,
    gate2: F64,
    c1: F64,
    c2: F64,
    ratio_octave: F64,
    factor: float,
) -> B:  # pragma: no cover - compiled
    """The monocular checks of CreateNewMapPoints on DLT points xyz (M, 3) world m (NaN: refused): in front of both
    cameras (T (4, 4) world -> camera, intr (fx, fy, cx, cy) of a pinhole pipeline image), the squared reprojection
    error to uv1 / uv2 (M, 2) px below gate1 / gate2 (M,) (chi2 x the level's sigma^2), both distances to the centres
    c1 / c2 (3,) positive and their ratio scale-consistent: not ratio_dist factor < ratio_octave nor ratio_dist >
    ratio_octave factor (ratio_octave (M,) kf1 / kf2 level scales). -> (M,) bool."""
    M = xyz.shape[0]
    ok = np.zeros(M, np.bool_)
    for i in range(M):
        x = xyz[i, 0]
        y = xyz[i, 1]
        z = xyz[i, 2]
        if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
            continue
        if not _reprojects(x, y, z, T1, intr1, uv1[i, 0], uv1[i, 1], gate1[i]):
            continue
        if not _reprojects(x, y, z, T2, intr2, uv2[i, 0], uv2[i, 1], gate2[i]):
            continue
        d1 = np.sqrt((x - c1[0]) ** 2 + (y - c1[1]) ** 2 + (z - c1[2]) ** 2)
        d2 = np.sqrt((x - c2[0]) ** 2 + (y - c2[1]) ** 2 + (z - c2[2]) ** 2)
        if not (d1 > 0 and d2 > 0):
            continue
        ratio_dist = d2 / (d1 if d1 > 1e-12 else 1e-12)
        if ratio_dist * factor < ratio_octave[i] or ratio_dist > ratio_octave[i] * factor:
            continue
        ok[i] = True
    return ok


@numba.njit(cache=True, nogil=True, inline="always")
def _reprojects(
    x: float, y: float, z: float, T: F64, intr: F64, u: float, v: float, gate: float
) -> bool:  # pragma: no cover - compiled
    """Point (x, y, z) world in front of camera T and projecting within sqrt(gate) px of (u, v) (pinhole
    ``u = fx X / Z + cx`` in this order; a non-finite projection counts as 1e9 px, as the numpy path)."""
    xc = x * T[0, 0] + y * T[0, 1] + z * T[0, 2] + T[0, 3]
    yc = x * T[1, 0] + y * T[1, 1] + z * T[1, 2] + T[1, 3]
    zc = x * T[2, 0] + y * T[2, 1] + z * T[2, 2] + T[2, 3]
    if not zc > 0:
        return False
    pu = intr[0] * xc / zc + intr[2]
    pv = intr[1] * yc / zc + intr[3]
    if not np.isfinite(pu):
        pu = 1e9
    if not np.isfinite(pv):
        pv = 1e9
    err2 = (pu - u) ** 2 + (pv - v) ** 2
    return err2 < gate
