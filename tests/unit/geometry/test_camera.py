"""Camera models against OpenCV (cv2.projectPoints / undistortPoints, cv2.fisheye) and their round trips."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray
from omegaconf import OmegaConf
from reference_cameras import EUROC, IDEAL, KITTI, TUM1, TUMVI

from slamkit.errors import ConfigError
from slamkit.geometry import KannalaBrandtCamera, PinholeCamera, camera_from_config
from slamkit.interfaces import Camera

F64 = NDArray[np.float64]

PINHOLES = [EUROC, TUM1, KITTI, IDEAL]

CV_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)


def pixel_grid(cam: Any, step: int = 16) -> F64:
    """Every ``step``-th pixel of the raw image, borders and corners included."""
    us = np.r_[np.arange(0, cam.width, step), cam.width - 1]
    vs = np.r_[np.arange(0, cam.height, step), cam.height - 1]
    return np.stack(np.meshgrid(us, vs), -1).reshape(-1, 2).astype(np.float64)


def points_in_view(cam: Any, n: int, seed: int) -> F64:
    """n points in front of a camera whose projections fall in its raw image (from unprojected pixels)."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform([0, 0], [cam.width - 1, cam.height - 1], size=(n, 2))
    return cam.unproject(uv) * rng.uniform(0.3, 30.0, size=(n, 1))


@pytest.mark.parametrize("cam", [*PINHOLES, TUMVI], ids=["euroc", "tum1", "kitti", "ideal", "tumvi"])
def test_cameras_satisfy_the_camera_protocol(cam: Any) -> None:
    assert isinstance(cam, Camera)
    assert cam.K.shape == (3, 3) and cam.K.dtype == np.float64


@pytest.mark.parametrize("cam", PINHOLES, ids=["euroc", "tum1", "kitti", "ideal"])
def test_pinhole_project_matches_cv2_project_points(cam: PinholeCamera) -> None:
    xyz = points_in_view(cam, 500, seed=1)
    ref, _ = cv2.projectPoints(xyz, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    uv = cam.project(xyz)
    assert uv.shape == (500, 2) and uv.dtype == np.float64
    np.testing.assert_allclose(uv, ref[:, 0], atol=1e-9)


@pytest.mark.parametrize("cam", PINHOLES, ids=["euroc", "tum1", "kitti", "ideal"])
def test_pinhole_undistort_matches_cv2_undistort_points(cam: PinholeCamera) -> None:
    uv = pixel_grid(cam)
    ref = cv2.undistortPoints(uv.reshape(-1, 1, 2), cam.K, cam.dist, P=cam.K, criteria=CV_CRITERIA)[:, 0]
    np.testing.assert_allclose(cam.undistort_points(uv), ref, atol=1e-6)


@pytest.mark.parametrize("cam", PINHOLES, ids=["euroc", "tum1", "kitti", "ideal"])
def test_pinhole_undistortion_is_exact_over_the_whole_image(cam: PinholeCamera) -> None:
    uv = pixel_grid(cam, step=8)
    und = cam.undistort_points(uv)
    assert np.all(np.isfinite(und))
    np.testing.assert_allclose(cam.distort_points(und), uv, atol=1e-6)
    np.testing.assert_allclose(cam.project(cam.unproject(uv)), uv, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(cam.unproject(uv), axis=1), 1.0, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(
    u=st.floats(0.0, 751.0),
    v=st.floats(0.0, 479.0),
    depth=st.floats(0.05, 1e3),
)
def test_pinhole_round_trips_property(u: float, v: float, depth: float) -> None:
    bearing = EUROC.unproject(np.array([u, v]))
    assert bearing.shape == (3,) and bearing[2] > 0
    np.testing.assert_allclose(EUROC.project(bearing * depth), [u, v], atol=1e-6)
    xyz = bearing * depth
    np.testing.assert_allclose(EUROC.unproject(EUROC.project(xyz)), xyz / np.linalg.norm(xyz), atol=1e-10)


def test_single_points_keep_their_rank() -> None:
    assert EUROC.project(np.array([0.1, 0.2, 2.0])).shape == (2,)
    assert EUROC.unproject(np.array([10.0, 20.0])).shape == (3,)
    assert EUROC.undistort_points(np.array([10.0, 20.0])).shape == (2,)
    assert EUROC.in_image(np.array([10.0, 20.0])).shape == ()
    assert TUMVI.project(np.array([0.1, 0.2, 2.0])).shape == (2,)


def test_points_behind_a_pinhole_have_no_pixel() -> None:
    uv = IDEAL.project(np.array([[0.1, 0.2, -2.0], [0.1, 0.2, 0.0], [0.1, 0.2, 2.0]]))
    assert np.all(np.isnan(uv[:2])) and np.all(np.isfinite(uv[2]))
    np.testing.assert_allclose(uv[2], [320.0 + 25.0, 240.0 + 50.0])


def test_strong_barrel_distortion_is_nan_beyond_its_fold() -> None:
    # r_d = r (1 - 0.4 r^2) peaks at r^2 = 1/1.2: beyond it two rays would share a pixel.
    cam = PinholeCamera(640, 480, 300.0, 300.0, 320.0, 240.0, [-0.4, 0.0, 0.0, 0.0])
    assert cam.r_max == pytest.approx(np.sqrt(1 / 1.2))
    inside, outside = 0.9 * cam.r_max, 1.1 * cam.r_max
    uv = cam.project(np.array([[inside, 0.0, 1.0], [outside, 0.0, 1.0]]))
    assert np.isfinite(uv[0, 0]) and np.isnan(uv[1, 0])
    np.testing.assert_allclose(cam.unproject(uv[0])[0] / cam.unproject(uv[0])[2], inside, atol=1e-12)
    # A pixel beyond the image of the fold (r_d > r_max (1 - 0.4 r_max^2)) has no ray.
    r_d_max = cam.r_max * (1 - 0.4 * cam.r_max**2)
    assert np.all(np.isnan(cam.unproject(np.array([320.0 + 300.0 * r_d_max * 1.01, 240.0]))))


def test_in_image_bounds_and_margin() -> None:
    uv = np.array([[0.0, 0.0], [639.9, 479.9], [640.0, 10.0], [-0.1, 10.0], [5.0, 5.0], [np.nan, 1.0]])
    np.testing.assert_array_equal(IDEAL.in_image(uv), [True, True, False, False, True, False])
    np.testing.assert_array_equal(IDEAL.in_image(uv, margin_px=5.0), [False, False, False, False, True, False])


def test_pinhole_parameters() -> None:
    assert EUROC.dist.shape == (5,) and EUROC.dist[4] == 0.0
    assert EUROC.is_distorted and not IDEAL.is_distorted
    np.testing.assert_array_equal(EUROC.K, [[458.654, 0, 367.215], [0, 457.296, 248.375], [0, 0, 1]])
    assert EUROC.model == "pinhole" and TUMVI.model == "kannala_brandt"
    with pytest.raises(ValueError):
        EUROC.dist[0] = 1.0  # read-only: a camera's calibration cannot change under its users


def test_kannala_brandt_project_matches_cv2_fisheye() -> None:
    rng = np.random.default_rng(3)
    xyz = rng.normal(size=(500, 3))
    xyz[:, 2] = np.abs(xyz[:, 2]) + 0.05  # cv2.fisheye divides by z: compare in front of the camera
    ref, _ = cv2.fisheye.projectPoints(xyz.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), TUMVI.K, TUMVI.k)
    np.testing.assert_allclose(TUMVI.project(xyz), ref[:, 0], atol=1e-9)


def test_kannala_brandt_undistort_matches_cv2_fisheye() -> None:
    uv = pixel_grid(TUMVI)
    ref = cv2.fisheye.undistortPoints(uv.reshape(-1, 1, 2), TUMVI.K, TUMVI.k, P=TUMVI.K, criteria=CV_CRITERIA)[:, 0]
    und = TUMVI.undistort_points(uv)
    front = TUMVI.unproject(uv)[:, 2] > 0.2  # keep away from 90 deg, where the pinhole image blows up
    assert front.sum() > 0.7 * len(uv)
    np.testing.assert_allclose(und[front], ref[front], atol=1e-6)
    np.testing.assert_allclose(TUMVI.distort_points(und[front]), uv[front], atol=1e-6)


@settings(max_examples=60, deadline=None)
@given(theta=st.floats(0.0, np.radians(110.0)), phi=st.floats(-np.pi, np.pi), depth=st.floats(0.05, 100.0))
def test_kannala_brandt_round_trip_including_rays_behind_the_image_plane(
    theta: float, phi: float, depth: float
) -> None:
    ray = np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
    uv = TUMVI.project(ray * depth)
    np.testing.assert_allclose(TUMVI.unproject(uv), ray, atol=1e-9)
    np.testing.assert_allclose(TUMVI.project(TUMVI.unproject(uv)), uv, atol=1e-6)


def test_kannala_brandt_special_rays() -> None:
    np.testing.assert_allclose(TUMVI.project(np.array([0.0, 0.0, 3.0])), [TUMVI.cx, TUMVI.cy])
    np.testing.assert_allclose(TUMVI.unproject(np.array([TUMVI.cx, TUMVI.cy])), [0.0, 0.0, 1.0])
    assert np.all(np.isnan(TUMVI.project(np.zeros(3))))
    # A ray at 100 deg exists for the fisheye but not for the ideal pinhole image.
    side = np.array([np.sin(np.radians(100.0)), 0.0, np.cos(np.radians(100.0))])
    assert np.all(np.isfinite(TUMVI.project(side)))
    assert np.all(np.isnan(TUMVI.undistort_points(TUMVI.project(side))))


def test_kannala_brandt_fold_limits_the_field_of_view() -> None:
    cam = KannalaBrandtCamera(640, 480, 200.0, 200.0, 320.0, 240.0, [-0.2, 0.0, 0.0, 0.0])
    assert cam.theta_max == pytest.approx(np.sqrt(1 / 0.6))  # 1 - 0.6 t^2 = 0
    beyond = cam.theta_max + 0.05
    assert np.all(np.isnan(cam.project(np.array([np.sin(beyond), 0.0, np.cos(beyond)]))))
    ok = cam.theta_max - 0.05
    uv = cam.project(np.array([np.sin(ok), 0.0, np.cos(ok)]))
    np.testing.assert_allclose(cam.unproject(uv), [np.sin(ok), 0.0, np.cos(ok)], atol=1e-9)


def test_config_round_trip_for_both_models() -> None:
    for cam in (EUROC, TUMVI):
        again = camera_from_config(cam.to_dict())
        assert type(again) is type(cam)
        np.testing.assert_array_equal(again.K, cam.K)
        np.testing.assert_array_equal(again.dist, cam.dist)
        assert (again.width, again.height) == (cam.width, cam.height)
    cfg = OmegaConf.create(
        {"width": 640, "height": 480, "fx": 500, "fy": 500, "cx": 320, "cy": 240, "dist": [0.1, 0, 0, 0]}
    )
    cam = camera_from_config(cfg)
    assert isinstance(cam, PinholeCamera) and cam.dist[0] == 0.1


BASE: dict[str, Any] = {"width": 640, "height": 480, "fx": 500.0, "fy": 500.0, "cx": 320.0, "cy": 240.0}


@pytest.mark.parametrize(
    ("cfg", "message"),
    [
        ({**BASE, "fx": -3}, "camera.fx: expected a positive number, got -3"),
        ({**BASE, "fy": "500"}, "camera.fy: expected a positive number, got '500'"),
        ({**BASE, "cx": float("nan")}, "camera.cx: expected a finite number"),
        ({**BASE, "width": 640.5}, "camera.width: expected a positive integer, got 640.5"),
        ({**BASE, "height": True}, "camera.height: expected a positive integer"),
        ({k: v for k, v in BASE.items() if k != "cy"}, "camera.cy: missing"),
        ({**BASE, "dist": [0.1, 0.2, 0.3]}, "camera.dist: expected 0 or 4 or 5 coefficients, got 3"),
        ({**BASE, "dist": [0.1, "x", 0, 0]}, "camera.dist[1]: expected a finite number"),
        ({**BASE, "model": "fisheye"}, "camera.model: expected 'pinhole' or 'kannala_brandt', got 'fisheye'"),
        ({**BASE, "k1": 0.1}, "camera.k1: unknown key for a pinhole camera"),
        ({**BASE, "model": "kannala_brandt"}, "camera.k: missing"),
        ({**BASE, "model": "kannala_brandt", "k": [0.0, 0.0, 0.0]}, "camera.k: expected 4 coefficients, got 3"),
    ],
)
def test_bad_config_names_the_key(cfg: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError) as info:
        camera_from_config(cfg)
    assert message in str(info.value)


def test_config_errors_use_the_given_key_and_constructor_validates() -> None:
    with pytest.raises(ConfigError, match=r"^camera_right\.fx: expected a positive number, got 0$"):
        camera_from_config({**BASE, "fx": 0}, key="camera_right")
    with pytest.raises(ConfigError, match=r"camera\.dist: expected 0 or 4 or 5 coefficients, got 2"):
        PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0, dist=[0.1, 0.2])
    with pytest.raises(ConfigError, match=r"camera\.fy: expected a positive number"):
        KannalaBrandtCamera(640, 480, 500.0, -1.0, 320.0, 240.0, k=[0, 0, 0, 0])


def test_bad_point_arrays_are_named() -> None:
    with pytest.raises(ValueError, match=r"xyz_c: expected an array of shape \(N, 3\) or \(3,\), got shape \(4, 2\)"):
        EUROC.project(np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"uv_px: expected an array of shape \(N, 2\)"):
        TUMVI.unproject(np.zeros((4, 3)))
