"""Two-view triangulation, parallax, cheirality and reprojection on scenes with known geometry."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from slamkit.geometry import (
    SE3,
    KannalaBrandtCamera,
    cheirality_mask,
    parallax_deg,
    reprojection_error_px,
    so3_exp,
    triangulate_points,
    triangulate_rays,
)

F64 = NDArray[np.float64]
K1 = np.array([[520.0, 0.0, 320.0], [0.0, 515.0, 240.0], [0.0, 0.0, 1.0]])
K2 = np.array([[450.0, 0.0, 300.0], [0.0, 455.0, 250.0], [0.0, 0.0, 1.0]])


def project(T_c_w: SE3, K: F64, xyz_w: F64) -> F64:
    h = T_c_w.act(xyz_w) @ K.T
    return h[:, :2] / h[:, 2:3]


def scene(seed: int, n: int = 200) -> tuple[SE3, SE3, F64]:
    """Two cameras looking down +z of the world, 0.5 m apart, and points 3-10 m in front of them."""
    rng = np.random.default_rng(seed)
    T_c1_w = SE3.exp(np.r_[rng.normal(scale=0.05, size=3), rng.normal(scale=0.1, size=3)])
    T_c2_w = SE3.exp(np.r_[rng.normal(scale=0.05, size=3), 0.5, 0.0, 0.0]) @ T_c1_w
    xyz_w = np.c_[rng.uniform(-3, 3, (n, 2)), rng.uniform(3, 10, n)]
    return T_c1_w, T_c2_w, xyz_w


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_triangulate_points_recovers_exact_points(seed: int) -> None:
    T1, T2, xyz = scene(seed)
    est = triangulate_points(T1.matrix(), T2.matrix(), K1, K2, project(T1, K1, xyz), project(T2, K2, xyz))
    np.testing.assert_allclose(est, xyz, atol=1e-8)
    assert np.all(cheirality_mask(T1, T2, est))


def test_triangulate_points_agrees_with_cv2() -> None:
    T1, T2, xyz = scene(3)
    rng = np.random.default_rng(0)
    uv1 = project(T1, K1, xyz) + rng.normal(scale=0.5, size=(len(xyz), 2))
    uv2 = project(T2, K2, xyz) + rng.normal(scale=0.5, size=(len(xyz), 2))
    est = triangulate_points(T1.matrix(), T2.matrix(), K1, K2, uv1, uv2)
    X = cv2.triangulatePoints(K1 @ T1.matrix()[:3], K2 @ T2.matrix()[:3], uv1.T, uv2.T)
    np.testing.assert_allclose(est, (X[:3] / X[3]).T, rtol=1e-6, atol=1e-6)
    err = reprojection_error_px(T1, K1, est, uv1)
    assert np.median(err) < 1.0


def test_triangulate_rays_with_fisheye_bearings_beyond_90_degrees() -> None:
    cam = KannalaBrandtCamera(512, 512, 190.0, 190.0, 256.0, 256.0, [0.0035, 0.0007, -0.002, 0.0002])
    T1 = SE3.identity()
    T2 = SE3.exp(np.array([0.0, 0.3, 0.0, -0.4, 0.05, 0.0]))
    # Points all around the first camera, including beside and slightly behind its image plane.
    rng = np.random.default_rng(1)
    xyz = rng.normal(size=(100, 3)) * 4.0
    xyz[:, 2] = np.abs(xyz[:, 2]) - 0.5
    rays1 = cam.unproject(cam.project(T1.act(xyz)))
    rays2 = cam.unproject(cam.project(T2.act(xyz)))
    ok = np.all(np.isfinite(rays1), axis=1) & np.all(np.isfinite(rays2), axis=1)
    assert ok.sum() > 80 and np.any(rays1[ok, 2] < 0)
    est = triangulate_rays(T1.matrix(), T2.matrix(), rays1[ok], rays2[ok])
    np.testing.assert_allclose(est, xyz[ok], atol=1e-7)


def test_triangulate_rays_accepts_unnormalised_bearings_and_single_points() -> None:
    T1, T2, xyz = scene(4, n=5)
    est = triangulate_rays(T1, T2, T1.act(xyz), 7.0 * T2.act(xyz))
    np.testing.assert_allclose(est, xyz, atol=1e-9)
    assert triangulate_rays(T1, T2, T1.act(xyz[0]), T2.act(xyz[0])).shape == (3,)


def test_parallel_rays_give_nan_not_a_point() -> None:
    T1 = SE3.identity()
    T2 = SE3(np.eye(3), np.array([-1.0, 0.0, 0.0]))  # camera 2 one metre to the right, same orientation
    ray = np.array([[0.1, 0.0, 1.0]])
    assert np.all(np.isnan(triangulate_rays(T1, T2, ray, ray)))
    uv = np.array([[330.0, 240.0]])
    assert np.all(np.isnan(triangulate_points(T1, T2, K1, K1, uv, uv)))
    assert np.all(np.isnan(triangulate_points(T1, T2, K1, K1, np.array([[np.nan, 1.0]]), uv)))


def test_parallax_of_known_configurations() -> None:
    c1, c2 = np.array([-1.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])
    pts = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, np.sqrt(3.0)], [0.0, 0.0, 1e6], [2.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    par = parallax_deg(pts, c1, c2)
    np.testing.assert_allclose(par[:4], [90.0, 60.0, 2e-6 * 180 / np.pi, 0.0], atol=1e-9)
    assert np.isnan(par[4])  # the point is on a camera centre
    assert parallax_deg(np.array([0.0, 0.0, 1.0]), c1, c2) == pytest.approx(90.0)


def test_cheirality_flags_points_behind_either_camera() -> None:
    T1 = SE3.identity()
    T2 = SE3(so3_exp(np.array([0.0, np.pi, 0.0])), np.array([0.0, 0.0, 2.0]))  # faces camera 1 from 2 m ahead
    # z in cam 2 = -z_w + 2 (rotation by pi about y flips z, then +2).
    pts = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 3.0], [0.0, 0.0, -1.0], [np.nan, 0.0, 1.0]])
    np.testing.assert_array_equal(cheirality_mask(T1.matrix(), T2.matrix(), pts), [True, False, False, False])


def test_reprojection_error_values() -> None:
    T = SE3.exp(np.array([0.1, -0.1, 0.05, 0.2, 0.1, 0.3]))
    xyz = np.array([[0.5, -0.2, 4.0], [1.0, 1.0, 6.0], [0.0, 0.0, -5.0]])
    uv = project(T, K1, xyz)
    uv[1] += [3.0, -4.0]
    err = reprojection_error_px(T.matrix(), K1, xyz, uv)
    np.testing.assert_allclose(err[:2], [0.0, 5.0], atol=1e-9)
    behind = T.inverse().act(np.array([0.0, 0.0, -5.0]))
    assert reprojection_error_px(T, K1, behind, np.array([320.0, 240.0])) == np.inf


def test_bad_shapes_are_named() -> None:
    T1, T2, xyz = scene(0, n=4)
    with pytest.raises(ValueError, match=r"uv1_px and uv2_px: expected the same number of rows, got 4 and 3"):
        triangulate_points(T1, T2, K1, K2, np.zeros((4, 2)), np.zeros((3, 2)))
    with pytest.raises(ValueError, match=r"K2: expected an array of shape \(3, 3\)"):
        triangulate_points(T1, T2, K1, np.eye(4), np.zeros((4, 2)), np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"T_c_w: expected an array of shape \(4, 4\)"):
        reprojection_error_px(np.eye(3), K1, xyz, np.zeros((4, 2)))
