"""Sim3 between two keyframes from matched 3D points, by Horn's closed form inside RANSAC (ORB-SLAM sec.
VII-B, Sim3Solver): three matches give a hypothesis; a match is an inlier when both its reprojections (point
of keyframe 2 into image 1 through S_12, point of keyframe 1 into image 2 through S_21) are within a
chi-square gate of its keypoints. Each image's projection is its keyframe's camera model (ORB-SLAM3 Sim3Solver:
mpCamera1 / mpCamera2->project): the pinhole K by default, or a given projection (a fisheye camera's raw image)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slamkit.geometry.alignment import horn_alignment
from slamkit.geometry.sim3 import Sim3

F64 = NDArray[np.float64]

#: A camera's projection into its pipeline image: (N, 3) m camera-frame points -> (uv (N, 2) px, valid (N,) bool)
#: (``Camera.project_image``).
Projection = Callable[[F64], tuple[F64, NDArray[np.bool_]]]

#: chi-square 99% with 2 dof, the per-image gate of ORB-SLAM's Sim3Solver (mvnMaxError1 = 9.210 sigma^2).
CHI2_2DOF_99 = 9.210


@dataclass(frozen=True)
class Sim3RansacResult:
    """S_12: the best hypothesis refined on its inliers (maps camera-2 points into camera 1), or None.
    inliers: (N,) bool. iterations: hypotheses tried."""

    S_12: Sim3 | None
    inliers: NDArray[np.bool_]
    iterations: int


def _project(K: F64, xyz: F64, project: Projection | None = None) -> tuple[F64, NDArray[np.bool_]]:
    if project is not None:
        uv_c, ok_c = project(xyz)
        return uv_c, ok_c & (xyz[:, 2] > 1e-9)
    z = xyz[:, 2]
    ok = z > 1e-9
    zs = np.where(ok, z, 1.0)
    uv = np.stack([K[0, 0] * xyz[:, 0] / zs + K[0, 2], K[1, 1] * xyz[:, 1] / zs + K[1, 2]], axis=1)
    return uv, ok


def sim3_inliers(
    S_12: Sim3,
    xyz1_c1: F64,
    xyz2_c2: F64,
    uv1_px: F64,
    uv2_px: F64,
    K1: F64,
    K2: F64,
    sigma2_1: F64,
    sigma2_2: F64,
    chi2: float = CHI2_2DOF_99,
    project1: Projection | None = None,
    project2: Projection | None = None,
) -> NDArray[np.bool_]:
    """(N,) bool: matches whose bidirectional reprojection errors are within ``chi2 * sigma^2`` in both images.
    project1 / project2: the cameras' projections (None: the pinhole K1 / K2)."""
    uv1, ok1 = _project(K1, S_12.act(xyz2_c2), project1)
    uv2, ok2 = _project(K2, S_12.inverse().act(xyz1_c1), project2)
    with np.errstate(invalid="ignore"):
        e1 = np.sum((uv1 - uv1_px) ** 2, axis=1)
        e2 = np.sum((uv2 - uv2_px) ** 2, axis=1)
        return ok1 & ok2 & (e1 < chi2 * sigma2_1) & (e2 < chi2 * sigma2_2)


def ransac_sim3(
    xyz1_c1: F64,
    xyz2_c2: F64,
    uv1_px: F64,
    uv2_px: F64,
    K1: F64,
    K2: F64,
    sigma2_1: F64,
    sigma2_2: F64,
    rng: np.random.Generator,
    fix_scale: bool = False,
    probability: float = 0.99,
    min_inliers: int = 20,
    max_iterations: int = 300,
    chi2: float = CHI2_2DOF_99,
    project1: Projection | None = None,
    project2: Projection | None = None,
) -> Sim3RansacResult:
    """Find S_12 with at least ``min_inliers`` inliers (ORB-SLAM: 0.99, 20, 300).

    xyz1_c1 / xyz2_c2: (N, 3) m, each match's map point in camera 1 / camera 2; uv1_px / uv2_px: (N, 2) the
    keypoints observing them, in each camera's pipeline image; sigma2_*: (N,) px^2 level variances; project1 /
    project2: the cameras' projections into those images (None: the pinhole K1 / K2). The iteration count adapts to
    the inlier ratio as RANSAC does; the best hypothesis is re-estimated on all its inliers.
    """
    n = xyz1_c1.shape[0]
    none = Sim3RansacResult(None, np.zeros(n, bool), 0)
    if n < max(3, min_inliers):
        return none
    best_inliers = np.zeros(n, bool)
    best: Sim3 | None = None
    needed = max_iterations
    it = 0
    while it < min(needed, max_iterations):
        it += 1
        sample = rng.choice(n, 3, replace=False)
        try:
            S = horn_alignment(xyz2_c2[sample], xyz1_c1[sample], with_scale=not fix_scale)
        except ValueError:  # collinear or degenerate sample
            continue
        inl = sim3_inliers(S, xyz1_c1, xyz2_c2, uv1_px, uv2_px, K1, K2, sigma2_1, sigma2_2, chi2, project1, project2)
        if inl.sum() > best_inliers.sum():
            best_inliers, best = inl, S
            ratio = inl.sum() / n
            if ratio >= 1.0:
                break
            # standard adaptive RANSAC bound for minimal sets of 3
            needed = int(np.ceil(np.log(1 - probability) / np.log(max(1 - ratio**3, 1e-12))))
    if best is None or best_inliers.sum() < min_inliers:
        return Sim3RansacResult(None, best_inliers, it)
    try:
        refined = horn_alignment(xyz2_c2[best_inliers], xyz1_c1[best_inliers], with_scale=not fix_scale)
    except ValueError:
        refined = best
    inl = sim3_inliers(refined, xyz1_c1, xyz2_c2, uv1_px, uv2_px, K1, K2, sigma2_1, sigma2_2, chi2, project1, project2)
    if inl.sum() >= best_inliers.sum():
        best, best_inliers = refined, inl
    return Sim3RansacResult(best, best_inliers, it)
