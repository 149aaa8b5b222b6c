"""Synthetic two-view correspondences from known cameras, for the twoview initializer tests."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pytest
from numpy.typing import NDArray

from slamkit.geometry import so3_exp, so3_log

F64 = NDArray[np.float64]

#: A 640 x 480 pinhole camera with fx = fy = 500 px (~65 deg horizontal field of view).
K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
WIDTH, HEIGHT = 640, 480


@dataclass(frozen=True)
class TwoViews:
    """Matches of points seen by a reference camera (the world frame) and a current camera.

    uv_ref, uv_cur: (M, 2) px (noisy, with outliers replacing some uv_cur); xyz_ref: (M, 3) m true points;
    R, t: true motion x_cur = R x_ref + t; outlier: (M,) bool, which matches were replaced.
    """

    uv_ref: F64
    uv_cur: F64
    xyz_ref: F64
    R: F64
    t: F64
    outlier: NDArray[np.bool_]


def project(xyz: F64) -> F64:
    h = xyz @ K.T
    out: F64 = h[:, :2] / h[:, 2:3]
    return out


def make_views(
    kind: str,
    *,
    seed: int = 0,
    n: int = 400,
    rotvec: tuple[float, float, float] = (0.02, -0.06, 0.01),
    t: tuple[float, float, float] = (0.6, 0.1, 0.0),
    noise_px: float = 0.0,
    outlier_fraction: float = 0.0,
    plane_normal: tuple[float, float, float] = (0.0, -1.0, 1.0),
    plane_distance_m: float = 3.0,
    depth_range_m: tuple[float, float] = (3.0, 8.0),
) -> TwoViews:
    """kind "plane": points on the plane n . x = d (reference frame; default a floor-like tilted plane);
    kind "general": points at random depths in ``depth_range_m`` over the whole image.
    Points are kept when they project inside the current image too. Gaussian noise ``noise_px`` (std per
    coordinate) in both images; ``outlier_fraction`` of uv_cur replaced by uniform random pixels."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform([0.0, 0.0], [WIDTH, HEIGHT], (n, 2))
    rays = np.c_[(uv - K[:2, 2]) / K[0, 0], np.ones(n)]
    if kind == "plane":
        normal = np.asarray(plane_normal) / np.linalg.norm(plane_normal)
        xyz = rays * (plane_distance_m / (rays @ normal))[:, None]
    elif kind == "general":
        xyz = rays * rng.uniform(*depth_range_m, n)[:, None]
    else:
        raise ValueError(kind)
    R = so3_exp(np.asarray(rotvec, dtype=np.float64))
    tv = np.asarray(t, dtype=np.float64)
    xyz_cur = xyz @ R.T + tv
    uv_cur = project(xyz_cur)
    keep = (xyz_cur[:, 2] > 0.1) & np.all((uv_cur >= 0) & (uv_cur < [WIDTH, HEIGHT]), axis=1)
    xyz, uv_ref, uv_cur = xyz[keep], project(xyz[keep]), uv_cur[keep]
    uv_ref = uv_ref + rng.normal(scale=noise_px, size=uv_ref.shape)
    uv_cur = uv_cur + rng.normal(scale=noise_px, size=uv_cur.shape)
    outlier = rng.random(len(xyz)) < outlier_fraction
    uv_cur[outlier] = rng.uniform([0.0, 0.0], [WIDTH, HEIGHT], (int(outlier.sum()), 2))
    return TwoViews(uv_ref, uv_cur, xyz, R, tv, outlier)


def rotation_error_deg(R_est: F64, R_true: F64) -> float:
    return float(np.degrees(np.linalg.norm(so3_log(R_est.T @ R_true))))


def direction_error_deg(t_est: F64, t_true: F64) -> float:
    c = float(t_est @ t_true / (np.linalg.norm(t_est) * np.linalg.norm(t_true)))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


@dataclass(frozen=True)
class Kit:
    """What the tests need from this module, handed out by the ``tv`` fixture (test modules do not
    import each other under pytest's importlib mode)."""

    K: F64
    make: Callable[..., TwoViews]
    rot_err_deg: Callable[[F64, F64], float]
    dir_err_deg: Callable[[F64, F64], float]
    project: Callable[[F64], F64]


@pytest.fixture
def tv() -> Kit:
    return Kit(K.copy(), make_views, rotation_error_deg, direction_error_deg, project)
