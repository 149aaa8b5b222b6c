"""Two-view geometry, vectorised over N correspondences: triangulation, parallax, cheirality, reprojection.

Poses are ``T_c_w`` (world -> camera, (4, 4) float64, or an ``SE3``); ``K`` is (3, 3) of the ideal
(undistorted) pinhole image, so pixel inputs here are undistorted px. Points are metres in the world frame.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from slamkit.geometry._checks import F64, as_matrix, as_points, same_length
from slamkit.geometry.se3 import SE3
from slamkit.geometry.so3 import hat

__all__ = [
    "cheirality_mask",
    "parallax_deg",
    "reprojection_error_px",
    "triangulate_points",
    "triangulate_rays",
]

#: A pose argument: a (4, 4) float64 matrix T_c_w or an SE3.
Pose = F64 | SE3

# |w| of the unit-norm homogeneous DLT solution below which the point is at infinity (NaN).
_AT_INFINITY = 1e-14


def _pose(T: Any, name: str) -> F64:
    """(4, 4) float64 from an SE3 or a (4, 4) array."""
    if isinstance(T, SE3):
        return T.matrix()
    return as_matrix(T, (4, 4), name)


def _solve_dlt(A: F64) -> F64:
    """A: (N, m, 4) homogeneous systems -> (N, 3) least-squares null vectors, dehomogenised.

    Rows with non-finite entries, or solutions at infinity, give NaN.
    """
    out = np.full((A.shape[0], 3), np.nan)
    ok = np.all(np.isfinite(A), axis=(1, 2))
    if np.any(ok):
        _, _, Vt = np.linalg.svd(A[ok])
        X = Vt[:, -1, :]  # right singular vector of the smallest singular value
        with np.errstate(invalid="ignore", divide="ignore"):
            pts = X[:, :3] / X[:, 3:4]
        pts[np.abs(X[:, 3]) <= _AT_INFINITY] = np.nan
        out[ok] = pts
    return out


def triangulate_points(T_c1_w: Pose, T_c2_w: Pose, K1: F64, K2: F64, uv1_px: F64, uv2_px: F64) -> F64:
    """Linear (DLT) triangulation of matched undistorted pixels, as ORB-SLAM's Triangulate.

    T_c1_w, T_c2_w: (4, 4) world -> camera poses; K1, K2: (3, 3); uv1_px, uv2_px: (N, 2) undistorted px.
    Each view with P = K [R | t] contributes u P[2] - P[0] and v P[2] - P[1]; the point is the right
    singular vector of the smallest singular value. Returns (N, 3) float64 xyz_w (m); NaN where the
    solution is at infinity (parallel rays) or the input is not finite. No cheirality check here.
    """
    P1 = as_matrix(K1, (3, 3), "K1") @ _pose(T_c1_w, "T_c1_w")[:3]
    P2 = as_matrix(K2, (3, 3), "K2") @ _pose(T_c2_w, "T_c2_w")[:3]
    uv1, single = as_points(uv1_px, 2, "uv1_px")
    uv2, _ = as_points(uv2_px, 2, "uv2_px")
    same_length(uv1, uv2, "uv1_px", "uv2_px")
    A = np.stack(
        [
            uv1[:, :1] * P1[2] - P1[0],
            uv1[:, 1:] * P1[2] - P1[1],
            uv2[:, :1] * P2[2] - P2[0],
            uv2[:, 1:] * P2[2] - P2[1],
        ],
        axis=1,
    )
    xyz = _solve_dlt(A)
    return xyz[0] if single else xyz


def triangulate_rays(T_c1_w: Pose, T_c2_w: Pose, rays1: F64, rays2: F64) -> F64:
    """Linear triangulation from bearing vectors (any camera model, including rays with z <= 0).

    T_c1_w, T_c2_w: (4, 4); rays1, rays2: (N, 3) bearings in each camera frame (any non-zero length).
    Each view contributes the three rows of hat(f) [R | t] (f x (R X + t) = 0), which stay well-posed for
    any ray direction. Returns (N, 3) xyz_w, NaN at infinity or for non-finite input. The DLT does not
    see the sign of a ray: check ``cheirality_mask`` or dot(ray, point) > 0 afterwards.
    """
    P1 = _pose(T_c1_w, "T_c1_w")[:3]
    P2 = _pose(T_c2_w, "T_c2_w")[:3]
    f1, single = as_points(rays1, 3, "rays1")
    f2, _ = as_points(rays2, 3, "rays2")
    same_length(f1, f2, "rays1", "rays2")
    with np.errstate(invalid="ignore", divide="ignore"):
        f1 = f1 / np.linalg.norm(f1, axis=1, keepdims=True)
        f2 = f2 / np.linalg.norm(f2, axis=1, keepdims=True)
    A = np.concatenate([hat(f1) @ P1, hat(f2) @ P2], axis=1)  # (N, 6, 4)
    xyz = _solve_dlt(A)
    return xyz[0] if single else xyz


def parallax_deg(xyz_w: F64, center1_w: F64, center2_w: F64) -> F64:
    """xyz_w: (N, 3); center1_w, center2_w: (3,) camera centres in the world (m) -> (N,) degrees.

    The angle at each point between the rays to the two centres, in [0, 180] (ORB-SLAM's parallax test
    uses its cosine); NaN for a point on a centre.
    """
    pts, single = as_points(xyz_w, 3, "xyz_w")
    a = pts - as_matrix(center1_w, (3,), "center1_w")
    b = pts - as_matrix(center2_w, (3,), "center2_w")
    cross = np.linalg.norm(np.cross(a, b), axis=1)
    dot = np.einsum("ij,ij->i", a, b)
    ang = np.degrees(np.arctan2(cross, dot))
    ang[(np.linalg.norm(a, axis=1) == 0) | (np.linalg.norm(b, axis=1) == 0)] = np.nan
    return ang[0] if single else ang


def _depth(T_c_w: F64, pts: F64) -> F64:
    out: F64 = pts @ T_c_w[2, :3] + T_c_w[2, 3]
    return out


def cheirality_mask(T_c1_w: Pose, T_c2_w: Pose, xyz_w: F64) -> NDArray[np.bool_]:
    """(N,) bool: the point has depth z > 0 in both cameras (False for NaN points)."""
    T1 = _pose(T_c1_w, "T_c1_w")
    T2 = _pose(T_c2_w, "T_c2_w")
    pts, single = as_points(xyz_w, 3, "xyz_w")
    with np.errstate(invalid="ignore"):
        ok = (_depth(T1, pts) > 0) & (_depth(T2, pts) > 0)
    return ok[0] if single else ok


def reprojection_error_px(T_c_w: Pose, K: F64, xyz_w: F64, uv_px: F64) -> F64:
    """Distance (px) between observed undistorted pixels and the pinhole projection of the points.

    T_c_w: (4, 4); K: (3, 3); xyz_w: (N, 3) m; uv_px: (N, 2) undistorted px -> (N,) float64 px.
    Points with depth <= 0 get +inf (so any threshold rejects them); NaN input gives NaN.
    """
    T = _pose(T_c_w, "T_c_w")
    Km = as_matrix(K, (3, 3), "K")
    pts, single = as_points(xyz_w, 3, "xyz_w")
    uv, _ = as_points(uv_px, 2, "uv_px")
    same_length(pts, uv, "xyz_w", "uv_px")
    xc = pts @ T[:3, :3].T + T[:3, 3]
    h = xc @ Km.T
    with np.errstate(invalid="ignore", divide="ignore"):
        proj = h[:, :2] / h[:, 2:3]
        err = np.linalg.norm(proj - uv, axis=1)
        err[xc[:, 2] <= 0] = np.inf
    return err[0] if single else err
