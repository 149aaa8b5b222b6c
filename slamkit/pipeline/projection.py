"""Guided matching by projection (ORB-SLAM ORBmatcher::SearchByProjection and the local-map frustum test).

All positions are in the camera's pipeline image (``Observations.uv_undist_px``; ``Camera.project_image``): the
undistorted pinhole image for a pinhole camera, the raw image for a Kannala-Brandt one.
"""

from __future__ import annotations

import dataclasses
import threading
import weakref
from dataclasses import dataclass
from typing import cast

import numba
import numpy as np
from numpy.typing import NDArray

from slamkit.errors import ConfigError
from slamkit.features import Features, Observations
from slamkit.geometry.camera import PinholeCamera
from slamkit.interfaces import Camera
from slamkit.pipeline.frame import ImageBounds
from slamkit.pipeline.map_points import predict_level
from slamkit.pipeline.matching import (
    GATE_REPROJECTION_CHI2,
    GATE_RIGHT_U,
    FeatureGrid,
    RightGate,
    WindowMatches,
    resolve_one_to_one,
    rotation_consistent,
    search_windows,
)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def project_points(T_c_w: F64, xyz_w: F64, camera: Camera) -> tuple[F64, F64, NDArray[np.bool_]]:
    """xyz_w: (N, 3) m world points seen from pose T_c_w through ``camera`` -> (uv (N, 2) px in the camera's
    pipeline image, z (N,) m depth in the camera, valid (N,) bool: in front and inside the model's field of view).
    """
    xyz_c = xyz_w @ T_c_w[:3, :3].T + T_c_w[:3, 3]
    uv, valid = camera.project_image(xyz_c)
    return uv, xyz_c[:, 2], valid


def require_pinhole_image(camera: Camera, step: str) -> None:
    """Raise ConfigError when ``camera``'s pipeline image is not the undistorted pinhole image: for the steps that
    still compute with K on undistorted pixels (two-view initialisation, triangulation, Sim3 loop verification),
    which would otherwise give wrong geometry for a fisheye camera's raw pixels."""
    if not camera.image_undistorted:
        raise ConfigError(
            f"{step}: the camera is {camera.model}, whose keypoints stay raw fisheye pixels; this step works on "
            "undistorted pinhole pixels only so far"
        )


@dataclass(frozen=True)
class ProjectionMatches:
    """Accepted matches: query rows (into the candidate arrays) and the feature indices they matched."""

    query: I64
    feature: I64
    distance: NDArray[np.int32]

    def __len__(self) -> int:
        return int(self.query.shape[0])


#: Grids of every keypoint of a features record (nothing taken), by (id(features), width, height, cell): the record's
#: weak reference, the grid and the indices of its keypoints. Bounded (oldest first out); see :func:`_free_grid`.
_FULL_GRIDS: dict[tuple[int, int, int, float], tuple[weakref.ref[Features], FeatureGrid, I64]] = {}
_FULL_GRIDS_MAX = 256
_FULL_GRIDS_LOCK = threading.Lock()  # local mapping's and loop closing's fusion may run in two threads


def _free_grid(
    features: Features, taken: NDArray[np.bool_], bounds: ImageBounds, cell_px: float, reuse: bool = False
) -> tuple[FeatureGrid, I64]:
    """The grid of the keypoints not ``taken`` and their indices. ``reuse``: the caller promises ``features`` is never
    modified (a keyframe's record): with nothing taken the grid is kept and handed out again for the same record
    (fusion searches each covisible keyframe's features once per new keyframe, the same grid every time)."""
    key = (id(features), int(np.ceil(bounds.max_u)), int(np.ceil(bounds.max_v)), float(cell_px))
    full = reuse and not taken.any()
    if full:
        with _FULL_GRIDS_LOCK:
            hit = _FULL_GRIDS.get(key)
        if hit is not None and hit[0]() is features:  # the id may be a dead record's: the weak reference tells
            return hit[1], hit[2]
    free = np.flatnonzero(~taken)
    grid = FeatureGrid.build(
        features.uv_undist_px[free],
        features.level[free],
        int(np.ceil(bounds.max_u)),
        int(np.ceil(bounds.max_v)),
        cell_px,
    )
    if full:
        with _FULL_GRIDS_LOCK:
            if len(_FULL_GRIDS) >= _FULL_GRIDS_MAX:
                del _FULL_GRIDS[next(iter(_FULL_GRIDS))]
            _FULL_GRIDS[key] = (weakref.ref(features), grid, free)
    return grid, free


def match_projected(
    features: Features,
    taken: NDArray[np.bool_],
    bounds: ImageBounds,
    uv_px: F64,
    descriptors: NDArray[np.uint8],
    radius_px: F64,
    min_level: I64,
    max_level: I64,
    max_distance: int,
    ratio: float | None,
    query_angle_deg: F64 | None,
    rotation_bins: int | None,
    cell_px: float = 10.0,
    ratio_same_level_only: bool = False,
    right_gate: RightGate | None = None,
    reuse_grid: bool = False,
) -> ProjectionMatches:
    """Match projected points (uv_px (Q, 2), descriptors (Q, D)) to the frame's features not ``taken``.

    Window radius and level range per query; Hamming threshold; optional ratio test (``ratio_same_level_only``:
    only where best and second-best lie on the same pyramid level, ORB-SLAM's SearchByProjection of the local map); when the queries carry
    keypoint angles (matching frame to frame), ORB-SLAM's rotation-consistency check with ``rotation_bins``
    (pipeline.matcher.rotation_bins; None when the queries carry no angles); each feature once.
    right_gate: the stereo/RGB-D candidate gate (:func:`right_u_gate`, :func:`fuse_reprojection_gate`) with its train
    arrays over all the frame's features; None (monocular): no gate.
    reuse_grid: ``features`` never changes (a keyframe's record): its grid is built once while nothing is ``taken``.
    """
    if uv_px.shape[0] == 0 or len(features) == 0:
        empty = np.zeros(0, np.int64)
        return ProjectionMatches(empty, empty, np.zeros(0, np.int32))
    grid, free = _free_grid(features, taken, bounds, cell_px, reuse_grid)
    if right_gate is not None:
        inv_s2 = right_gate.train_inv_sigma2
        right_gate = dataclasses.replace(
            right_gate,
            train_u_right_px=right_gate.train_u_right_px[free],
            train_inv_sigma2=None if inv_s2 is None else inv_s2[free],
        )
    m: WindowMatches = search_windows(
        grid, features.descriptors[free], uv_px, descriptors, radius_px, min_level, max_level, right_gate
    )
    ok = m.accepted(max_distance, ratio, ratio_same_level_only)
    q = np.flatnonzero(ok)
    f = free[m.best_index[q]]
    d = m.best_distance[q]
    keep = resolve_one_to_one(q, f, d)
    q, f, d = q[keep], f[keep], d[keep]
    if query_angle_deg is not None and q.size:
        if rotation_bins is None:
            raise ValueError("match_projected: query angles given without rotation_bins")
        rot = rotation_consistent(query_angle_deg[q] - features.angle_deg[f].astype(np.float64), rotation_bins)
        q, f, d = q[rot], f[rot], d[rot]
    return ProjectionMatches(q.astype(np.int64), f.astype(np.int64), d)


def predicted_u_right(uv_px: F64, z_m: F64, bf: float) -> F64:
    """(Q,) px: the right-image u of points projecting at uv_px (Q, 2) with depth z_m (Q,) m in a rectified pair
    (or RGB-D's virtual one) of baseline x fx ``bf`` (m px): u - bf / z (ORB-SLAM2 mTrackProjXR, Fuse's ur)."""
    return uv_px[:, 0] - bf / z_m


def right_u_gate(features: Observations, query_u_right_px: F64, tolerance_px: F64) -> RightGate:
    """ORB-SLAM2 SearchByProjection's stereo check: a candidate with a right coordinate (``features.u_right_px``
    finite) is skipped when it differs from the query's predicted one by more than the query's tolerance (the
    search radius at its level)."""
    return RightGate(GATE_RIGHT_U, query_u_right_px, features.u_right_px.astype(np.float64), tolerance_px=tolerance_px)


def fuse_reprojection_gate(
    features: Observations, query_u_right_px: F64, chi2_mono: float, chi2_stereo: float
) -> RightGate:
    """ORB-SLAM2 Fuse(pKF, vpMapPoints)'s check of each candidate: (du^2 + dv^2 [+ du_R^2]) / sigma^2 of its level
    at most ``chi2_stereo`` (3 dof, a candidate with a right coordinate) or ``chi2_mono`` (2 dof)."""
    return RightGate(
        GATE_REPROJECTION_CHI2,
        query_u_right_px,
        features.u_right_px.astype(np.float64),
        train_inv_sigma2=1.0 / features.level_sigma2(),
        chi2_mono=chi2_mono,
        chi2_stereo=chi2_stereo,
    )


@dataclass(frozen=True)
class FrustumTest:
    """The local-map visibility test of ORB-SLAM V-D for a set of map points seen from a camera pose.

    visible: (Q,) bool, passes the five filters' geometric part (in image, depth > 0, distance in the
    scale-invariance range, viewing angle); uv_px, predicted_level, view_cos and z_m (depth in the camera, m) for
    each point.
    """

    visible: NDArray[np.bool_]
    uv_px: F64
    predicted_level: I64
    view_cos: F64
    z_m: F64


def frustum_test(
    T_c_w: F64,
    camera: Camera,
    bounds: ImageBounds,
    xyz_w: F64,
    normal_w: F64,
    d_min_m: F64,
    d_max_m: F64,
    min_view_cos: float,
    scale_factor: float,
    n_levels: int,
) -> FrustumTest:
    """ORB-SLAM Frame::isInFrustum for many points: (1) projects inside the image with positive depth,
    (3) distance within [0.8 d_min, 1.2 d_max], (2) viewing angle v.n >= min_view_cos (cos 60 deg),
    (4) predicted pyramid level from the distance. Filter (5), the descriptor match, is ``match_projected``."""
    if type(camera).project_image is PinholeCamera.project_image:
        # the pinhole model's arithmetic in one compiled pass; the products that numpy hands to BLAS / einsum's
        # kernels (which may fuse multiply-adds) stay numpy calls, so every value is the same bit for bit
        xyz_c = xyz_w @ T_c_w[:3, :3].T + T_c_w[:3, 3]  # project_points' expression
        center = -T_c_w[:3, :3].T @ T_c_w[:3, 3]
        ray = xyz_w - center
        dot = np.einsum("ij,ij->i", ray, normal_w)
        p = cast(PinholeCamera, camera)
        uv, dist, view_cos, ok = _pinhole_frustum(
            xyz_c, ray, dot, np.asarray(d_min_m, np.float64), np.asarray(d_max_m, np.float64),
            float(p.fx), float(p.fy), float(p.cx), float(p.cy),
            float(bounds.min_u), float(bounds.max_u), float(bounds.min_v), float(bounds.max_v), float(min_view_cos),
        )  # fmt: skip
        level = predict_level(d_max_m, dist, scale_factor, n_levels)
        return FrustumTest(ok, uv, level, view_cos, xyz_c[:, 2])
    uv, z, valid = project_points(T_c_w, xyz_w, camera)
    center = -T_c_w[:3, :3].T @ T_c_w[:3, 3]
    ray = xyz_w - center
    dist = np.linalg.norm(ray, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        view_cos = np.einsum("ij,ij->i", ray, normal_w) / dist
    ok = valid.copy()
    ok &= bounds.contains(np.where(np.isfinite(uv), uv, -1e9))
    ok &= (dist >= 0.8 * d_min_m) & (dist <= 1.2 * d_max_m)
    ok &= view_cos >= min_view_cos
    level = predict_level(d_max_m, dist, scale_factor, n_levels)
    return FrustumTest(ok, uv, level, view_cos, z)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _pinhole_frustum(
    xyz_c: F64,
    ray: F64,
    dot: F64,
    d_min_m: F64,
    d_max_m: F64,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    min_u: float,
    max_u: float,
    min_v: float,
    max_v: float,
    min_view_cos: float,
) -> tuple[F64, F64, F64, NDArray[np.bool_]]:  # pragma: no cover - compiled
    """:func:`frustum_test`'s elementwise part for a pinhole camera (``PinholeCamera.project_image``), per point i:
    xyz_c (N, 3) m the point in the camera, ray (N, 3) m camera centre -> point (world), dot (N,) ray . normal_w.
    -> (uv (N, 2) px: u = fx x / z + cx, v = fy y / z + cy; dist (N,) m = |ray| (np.linalg.norm's sum order);
    view_cos (N,) = dot / dist; ok (N,): z > 0, finite uv inside [min_u, max_u) x [min_v, max_v),
    0.8 d_min <= dist <= 1.2 d_max, view_cos >= min_view_cos). The same IEEE operations in the same order as the
    numpy expressions of project_points / PinholeCamera.project_image / ImageBounds.contains / frustum_test."""
    n = xyz_c.shape[0]
    uv = np.empty((n, 2))
    dist = np.empty(n)
    view_cos = np.empty(n)
    ok = np.empty(n, np.bool_)
    for i in range(n):
        z = xyz_c[i, 2]
        u = fx * xyz_c[i, 0] / z + cx
        v = fy * xyz_c[i, 1] / z + cy
        uv[i, 0] = u
        uv[i, 1] = v
        rx = ray[i, 0]
        ry = ray[i, 1]
        rz = ray[i, 2]
        d = np.sqrt(rx * rx + ry * ry + rz * rz)
        dist[i] = d
        c = dot[i] / d
        view_cos[i] = c
        inside = np.isfinite(u) and np.isfinite(v) and u >= min_u and u < max_u and v >= min_v and v < max_v
        ok[i] = z > 0 and inside and d >= 0.8 * d_min_m[i] and d <= 1.2 * d_max_m[i] and c >= min_view_cos
    return uv, dist, view_cos, ok


def radius_by_viewing_cos(view_cos: F64) -> F64:
    """ORB-SLAM's search radius factor: 2.5 when the point is seen almost head-on (cos > 0.998), else 4."""
    return np.where(view_cos > 0.998, 2.5, 4.0)
