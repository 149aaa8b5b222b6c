"""Triangulate and grade each motion hypothesis, then pick a clear winner or refuse (ORB-SLAM sec. IV-4).

The grading mirrors ORB-SLAM's Initializer::CheckRT: a model inlier is a *good* point when its DLT
triangulation is finite, in front of both cameras (waived for near-parallel rays, whose depth sign is
unreliable) and reprojects within the threshold in both images. Good points whose rays are not
near-parallel are the *triangulated* ones that may become map points. Geometry comes from
slamkit.geometry.twoview; the reference camera is the world frame here (T_ref_ref = I).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slamkit.geometry.se3 import invert_T
from slamkit.geometry.twoview import (
    _AT_INFINITY,
    cheirality_mask,
    parallax_deg,
    reprojection_error_px,
    triangulate_points,
)
from slamkit_twoview.screen import screen_points

F64 = NDArray[np.float64]
_IDENTITY = np.eye(4)


@dataclass(frozen=True)
class HypothesisCheck:
    """Grading of one (R, t) hypothesis over the M input matches.

    n_good: number of good points; parallax_deg: the hypothesis' parallax (the ``parallax_rank``-th
    largest parallax among good points, 0 when none); xyz_ref: (M, 3) m in the reference camera, NaN
    where not triangulated; triangulated: (M,) bool, good and not near-parallel.
    """

    n_good: int
    parallax_deg: float
    xyz_ref: F64
    triangulated: NDArray[np.bool_]


def pose_matrix(R: F64, t: F64) -> F64:
    """(3, 3), (3,) -> (4, 4) T_cur_ref = [[R, t], [0, 1]]."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _projective_reprojection_px(T_c_ref: F64, K: F64, xyz_ref: F64, uv_px: F64) -> F64:
    """Reprojection error (px) that ignores the depth sign, as ORB-SLAM's CheckRT computes it.

    A point behind the camera projects like its mirror image through the camera centre
    (x_c -> -x_c), so points with depth <= 0 are reflected there before ``reprojection_error_px``.
    Only near-parallel rays reach this test with a negative depth.
    """
    center = invert_T(T_c_ref)[:3, 3]
    depth = xyz_ref @ T_c_ref[2, :3] + T_c_ref[2, 3]
    with np.errstate(invalid="ignore"):
        behind = depth <= 0
    pts = np.where(behind[:, None], 2.0 * center - xyz_ref, xyz_ref)
    return reprojection_error_px(T_c_ref, K, pts, uv_px)


def check_motion(
    R: F64,
    t: F64,
    K: F64,
    uv_ref_px: F64,
    uv_cur_px: F64,
    inliers: NDArray[np.bool_],
    *,
    max_reproj_err_px: float,
    max_cos_parallax: float,
    parallax_rank: int,
) -> HypothesisCheck:
    """Triangulate the model inliers under x_cur = R x_ref + t and grade them (ORB-SLAM CheckRT).

    R: (3, 3); t: (3,); K: (3, 3); uv_ref_px, uv_cur_px: (M, 2) undistorted px; inliers: (M,) bool.
    max_cos_parallax: rays with cos(parallax) >= this are near-parallel (depth test waived, not
    triangulated). parallax_rank: the hypothesis parallax is that of the (rank+1)-th most-parallax good point.
    """
    M = uv_ref_px.shape[0]
    T_cur_ref = pose_matrix(R, t)
    idx = np.flatnonzero(inliers)
    xyz_all = np.full((M, 3), np.nan)
    triangulated = np.zeros(M, dtype=bool)
    if idx.size == 0:
        return HypothesisCheck(0, 0.0, xyz_all, triangulated)

    xyz = triangulate_points(_IDENTITY, T_cur_ref, K, K, uv_ref_px[idx], uv_cur_px[idx])
    par, near_parallel, good = _point_tests(
        T_cur_ref, K, xyz, uv_ref_px[idx], uv_cur_px[idx], max_reproj_err_px, max_cos_parallax
    )
    n_good = int(good.sum())
    parallax = 0.0
    if n_good > 0:
        ranked = np.sort(par[good])[::-1]  # largest parallax first (ORB-SLAM sorts cosines ascending)
        parallax = float(ranked[min(parallax_rank, n_good - 1)])
    tri = good & ~near_parallel
    triangulated[idx[tri]] = True
    xyz_all[idx[tri]] = xyz[tri]
    return HypothesisCheck(n_good, parallax, xyz_all, triangulated)


def _point_tests(
    T_cur_ref: F64, K: F64, xyz: F64, uv_ref_px: F64, uv_cur_px: F64, max_reproj_err_px: float, max_cos_parallax: float
) -> tuple[F64, NDArray[np.bool_], NDArray[np.bool_]]:
    """CheckRT's tests of N triangulated points (N, 3) in the reference camera, observed at (N, 2) px in each image ->
    (parallax (N,) degrees, near_parallel (N,), good (N,)). Each row's result depends on that row's inputs only."""
    finite = np.all(np.isfinite(xyz), axis=1)
    with np.errstate(invalid="ignore"):
        par = parallax_deg(xyz, np.zeros(3), invert_T(T_cur_ref)[:3, 3])
        near_parallel = np.cos(np.radians(par)) >= max_cos_parallax
        in_front = cheirality_mask(_IDENTITY, T_cur_ref, xyz)
        err_ref = _projective_reprojection_px(_IDENTITY, K, xyz, uv_ref_px)
        err_cur = _projective_reprojection_px(T_cur_ref, K, xyz, uv_cur_px)
        good = finite & (in_front | near_parallel) & (err_ref <= max_reproj_err_px) & (err_cur <= max_reproj_err_px)
    return par, near_parallel, good


def exact_points(R: F64, t: F64, K: F64, uv_ref_px: F64, uv_cur_px: F64, triangulated: NDArray[np.bool_]) -> F64:
    """(M, 3) m in the reference camera: the triangulated matches' points as ``check_motion`` computes them (its DLT,
    row by row the same arithmetic), NaN elsewhere. R: (3, 3), t: (3,); uv_*: (M, 2) px; triangulated: (M,) bool."""
    xyz_all = np.full((uv_ref_px.shape[0], 3), np.nan)
    rows = np.flatnonzero(triangulated)
    if rows.size:
        xyz_all[rows] = triangulate_points(_IDENTITY, pose_matrix(R, t), K, K, uv_ref_px[rows], uv_cur_px[rows])
    return xyz_all


def check_motion_screened(
    R: F64,
    t: F64,
    K: F64,
    uv_ref_px: F64,
    uv_cur_px: F64,
    inliers: NDArray[np.bool_],
    *,
    max_reproj_err_px: float,
    max_cos_parallax: float,
    parallax_rank: int,
) -> HypothesisCheck:
    """``check_motion``'s n_good, parallax and triangulated mask, with LAPACK's SVD only where it decides something.

    Every inlier is triangulated and graded by the compiled screen (screen.py); the points it leaves ``unsure`` (a test
    too close to its threshold for its solution to decide), and those whose parallax may be the hypothesis' ranked
    one, get ``check_motion``'s own arithmetic: their DLT solved as there, and the tests run on all the inliers' rows
    at the same positions. The result's xyz_ref is NaN throughout (``exact_points`` gives the points of the hypothesis
    kept). Falls back to ``check_motion`` if the ranked parallax cannot be told from the screened values.
    """
    M = uv_ref_px.shape[0]
    idx = np.flatnonzero(inliers)
    triangulated = np.zeros(M, dtype=bool)
    xyz_none = np.full((M, 3), np.nan)
    if idx.size == 0:
        return HypothesisCheck(0, 0.0, xyz_none, triangulated)
    T_cur_ref = pose_matrix(R, t)
    P1 = K @ _IDENTITY[:3]
    P2 = K @ T_cur_ref[:3]
    center2 = invert_T(T_cur_ref)[:3, 3]
    uv1 = np.ascontiguousarray(uv_ref_px[idx], dtype=np.float64)
    uv2 = np.ascontiguousarray(uv_cur_px[idx], dtype=np.float64)
    xyz, par, par_margin, good, near, unsure = screen_points(
        P1, P2, center2, uv1, uv2, float(max_reproj_err_px), float(max_cos_parallax), _AT_INFINITY
    )
    exact = np.zeros(idx.size, dtype=bool)
    center1 = np.zeros(3)

    def solve(rows: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """The rows' points by check_motion's DLT (row by row its arithmetic); returns the rows new to it."""
        new = rows & ~exact
        if new.any():
            xyz[new] = triangulate_points(_IDENTITY, T_cur_ref, K, K, uv1[new], uv2[new])
            par_margin[new] = 0.0
            exact[new] = True
        return new

    new = solve(unsure)
    if new.any():  # their tests by check_motion's arithmetic, run on every row (each at its position there)
        p, n, g = _point_tests(T_cur_ref, K, xyz, uv1, uv2, max_reproj_err_px, max_cos_parallax)
        par[new], near[new], good[new] = p[new], n[new], g[new]
    n_good = int(good.sum())
    parallax = 0.0
    if n_good > 0:
        k = min(parallax_rank, n_good - 1)
        # each exact parallax lies in [par - w, par + w] (w: the screen's margin, radians, x10 for safety; 0 where
        # solved exactly), so the exact k-th largest lies between the k-th largest lower and upper ends: a point whose
        # interval lies wholly above (below) that range is above (below) it; the rest are solved exactly
        w = np.degrees(10.0 * par_margin) + 1e-12 * (par_margin > 0)
        lo, hi = par - w, par + w
        kth_lo = float(np.sort(lo[good])[::-1][k])
        kth_hi = float(np.sort(hi[good])[::-1][k])
        above = good & (lo > kth_hi)
        band = good & ~above & (hi >= kth_lo)
        if solve(band).any():
            # check_motion's parallax arithmetic, on every row (each at its position there)
            par[band] = parallax_deg(xyz, center1, center2)[band]
        ranked = np.sort(par[band])[::-1]
        n_above = int(above.sum())
        if not 0 <= k - n_above < ranked.size:
            return check_motion(
                R,
                t,
                K,
                uv_ref_px,
                uv_cur_px,
                inliers,
                max_reproj_err_px=max_reproj_err_px,
                max_cos_parallax=max_cos_parallax,
                parallax_rank=parallax_rank,
            )
        parallax = float(ranked[k - n_above])
    triangulated[idx[good & ~near]] = True
    return HypothesisCheck(n_good, parallax, xyz_none, triangulated)


@dataclass(frozen=True)
class Selection:
    """Outcome of the choice among hypotheses: ``best`` index (None when refused) and why it was refused."""

    best: int | None
    failures: list[str]


def select_from_homography(
    checks: list[HypothesisCheck],
    n_inliers: int,
    *,
    second_best_ratio: float,
    min_good_fraction: float,
    min_triangulated: int,
    min_parallax_deg: float,
) -> Selection:
    """ORB-SLAM2 Initializer::ReconstructH: accept the best of the 8 only when
    second_best < ratio * best, parallax >= min_parallax, best > min_triangulated and best > fraction * N."""
    n_good = np.array([c.n_good for c in checks])
    best = int(np.argmax(n_good))  # first of ties, as ORB-SLAM's strict `nGood > bestGood`
    best_good = int(n_good[best])
    second = int(np.max(np.delete(n_good, best))) if len(checks) > 1 else 0
    parallax = checks[best].parallax_deg
    failures = []
    if not second < second_best_ratio * best_good:
        failures.append(
            f"ambiguous motion (twofold planar ambiguity): second-best hypothesis has {second} good points, "
            f"not < {second_best_ratio} x best {best_good}"
        )
    if not parallax >= min_parallax_deg:
        failures.append(f"low parallax: {parallax:.3g} deg < min_parallax_deg {min_parallax_deg}")
    if not best_good > min_triangulated:
        failures.append(f"too few triangulated points: {best_good} <= min_triangulated {min_triangulated}")
    if not best_good > min_good_fraction * n_inliers:
        failures.append(
            f"too few good points: {best_good} of {n_inliers} homography inliers "
            f"(needs > {min_good_fraction:g} of them)"
        )
    return Selection(None if failures else best, failures)


def select_from_fundamental(
    checks: list[HypothesisCheck],
    n_inliers: int,
    *,
    similar_ratio: float,
    min_good_fraction: float,
    min_triangulated: int,
    min_parallax_deg: float,
) -> Selection:
    """ORB-SLAM2 Initializer::ReconstructF: accept the best of the 4 only when no other hypothesis has
    more than ratio * best good points, best >= max(int(fraction * N), min_triangulated) and its parallax
    > min_parallax."""
    n_good = np.array([c.n_good for c in checks])
    best = int(np.argmax(n_good))
    best_good = int(n_good[best])
    n_similar = int(np.sum(n_good > similar_ratio * best_good))
    n_min_good = max(int(min_good_fraction * n_inliers), min_triangulated)
    parallax = checks[best].parallax_deg
    failures = []
    if n_similar > 1:
        failures.append(
            f"ambiguous motion: {n_similar} of {len(checks)} hypotheses have > {similar_ratio} x the best's "
            f"{best_good} good points (counts {n_good.tolist()})"
        )
    if best_good < n_min_good:
        failures.append(
            f"too few good points: {best_good} < max({min_good_fraction:g} x {n_inliers} fundamental inliers, "
            f"min_triangulated {min_triangulated})"
        )
    if not parallax > min_parallax_deg:
        failures.append(f"low parallax: {parallax:.3g} deg <= min_parallax_deg {min_parallax_deg}")
    return Selection(None if failures else best, failures)
