"""The pipeline's image of each camera model (Camera.project_image / unproject_image / project_image_jacobian /
image_bounds): projections against the models' own raw projection, Jacobians against central finite differences,
bearings back onto the same pixels, and the pinhole path bit for bit as the pipeline computed it before."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray
from reference_cameras import EUROC, IDEAL, TUMVI

from slamkit.geometry import KannalaBrandtCamera
from slamkit.interfaces import Camera

F64 = NDArray[np.float64]

# a strongly distorted fisheye, so that every term of the model shows in the Jacobian
STRONG_KB = KannalaBrandtCamera(640, 480, 300.0, 310.0, 330.0, 235.0, [0.08, -0.02, 0.004, -0.0003])
CAMERAS: list[Camera] = [IDEAL, EUROC, TUMVI, STRONG_KB]


def points_in_view(n: int, max_angle_deg: float, seed: int = 0) -> F64:
    """(n, 3) m camera-frame points within ``max_angle_deg`` of the optical axis, 0.5-8 m away."""
    rng = np.random.default_rng(seed)
    theta = np.radians(max_angle_deg) * np.sqrt(rng.uniform(0.0, 1.0, n))
    phi = rng.uniform(-np.pi, np.pi, n)
    d = rng.uniform(0.5, 8.0, n)
    return np.stack([d * np.sin(theta) * np.cos(phi), d * np.sin(theta) * np.sin(phi), d * np.cos(theta)], axis=1)


def max_angle(camera: Camera) -> float:
    return 80.0 if not camera.image_undistorted else 35.0


@pytest.mark.parametrize("camera", CAMERAS, ids=lambda c: c.model + str(c.width))
def test_jacobian_matches_central_differences(camera: Camera) -> None:
    xyz = points_in_view(300, max_angle(camera))
    J = camera.project_image_jacobian(xyz)
    assert J.shape == (300, 2, 3)
    h = 1e-6
    numeric = np.empty_like(J)
    for a in range(3):
        step = np.zeros(3)
        step[a] = h
        plus, _ = camera.project_image(xyz + step)
        minus, _ = camera.project_image(xyz - step)
        numeric[:, :, a] = (plus - minus) / (2.0 * h)
    scale = np.abs(numeric).max(axis=(1, 2), keepdims=True)
    np.testing.assert_allclose(J / scale, numeric / scale, atol=1e-7)


@pytest.mark.parametrize("camera", [TUMVI, STRONG_KB], ids=lambda c: c.model + str(c.width))
def test_fisheye_jacobian_on_and_near_the_optical_axis(camera: Camera) -> None:
    xyz = np.array([[0.0, 0.0, 2.0], [1e-13, -1e-13, 2.0], [1e-7, 2e-7, 3.0]])
    J = camera.project_image_jacobian(xyz)
    assert np.all(np.isfinite(J))
    fx, fy = camera.K[0, 0], camera.K[1, 1]
    # on the axis theta_d ~ theta ~ r / z: the pinhole Jacobian (fx / z, fy / z on the diagonal)
    np.testing.assert_allclose(J[0], [[fx / 2.0, 0.0, 0.0], [0.0, fy / 2.0, 0.0]], atol=1e-9)
    np.testing.assert_allclose(J[1], J[0], atol=1e-6)
    np.testing.assert_allclose(J[2, :, :2], [[fx / 3.0, 0.0], [0.0, fy / 3.0]], rtol=1e-6, atol=1e-6)


def test_fisheye_projects_into_the_raw_image_with_its_model() -> None:
    xyz = points_in_view(500, 95.0)
    for camera in (TUMVI, STRONG_KB):
        uv, valid = camera.project_image(xyz)
        raw = camera.project(xyz)
        front = xyz[:, 2] > 0
        np.testing.assert_array_equal(valid, front & np.all(np.isfinite(raw), axis=1))
        np.testing.assert_array_equal(uv[valid], raw[valid])
        # a wide ray is far from where a pinhole with the same K would put it
        wide = valid & (np.degrees(np.arctan2(np.hypot(xyz[:, 0], xyz[:, 1]), xyz[:, 2])) > 60.0)
        pinhole = xyz[wide, :2] / xyz[wide, 2:] * np.diag(camera.K)[:2] + camera.K[:2, 2]
        assert np.all(np.linalg.norm(pinhole - uv[wide], axis=1) > 20.0)
        assert camera.image_bounds() == (0.0, float(camera.width), 0.0, float(camera.height))


def test_points_behind_or_outside_the_field_of_view_are_not_valid() -> None:
    xyz = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.3, 0.2, -0.5], [0.1, 0.1, 2.0], [np.nan, 0.0, 1.0]])
    for camera in CAMERAS:
        _, valid = camera.project_image(xyz)
        np.testing.assert_array_equal(valid, [False, False, False, True, False])
    narrow = KannalaBrandtCamera(640, 480, 300.0, 300.0, 320.0, 240.0, [-0.3, 0.0, 0.0, 0.0])  # folds at 1.054 rad
    _, valid = narrow.project_image(np.array([[np.tan(1.2), 0.0, 1.0], [np.tan(0.5), 0.0, 1.0]]))
    np.testing.assert_array_equal(valid, [False, True])


@pytest.mark.parametrize("camera", CAMERAS, ids=lambda c: c.model + str(c.width))
def test_bearings_of_projections_are_the_rays(camera: Camera) -> None:
    xyz = points_in_view(400, max_angle(camera), seed=3)
    uv, valid = camera.project_image(xyz)
    assert valid.all()
    bearing = camera.unproject_image(uv)
    np.testing.assert_allclose(np.linalg.norm(bearing, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(bearing, xyz / np.linalg.norm(xyz, axis=1, keepdims=True), atol=1e-9)


def test_pinhole_image_is_the_undistorted_image_bit_for_bit() -> None:
    """The pipeline used to compute u = K[0, 0] * x / z + K[0, 2] on camera points; the regression oracle (identical
    trajectories) depends on project_image doing exactly that."""
    rng = np.random.default_rng(7)
    xyz = rng.normal(size=(1000, 3)) * [2.0, 2.0, 3.0]
    for camera in (IDEAL, EUROC):
        K = camera.K
        z = xyz[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            before = np.stack([K[0, 0] * xyz[:, 0] / z + K[0, 2], K[1, 1] * xyz[:, 1] / z + K[1, 2]], axis=1)
        uv, valid = camera.project_image(xyz)
        np.testing.assert_array_equal(uv, before)
        np.testing.assert_array_equal(valid, z > 0)
        # the undistorted image of a distorted camera: its raw projection undistorted again
        near = valid & (np.hypot(xyz[:, 0], xyz[:, 1]) < 0.5 * np.abs(z))  # inside the distortion's one-to-one radius
        np.testing.assert_allclose(camera.undistort_points(camera.project(xyz[near])), uv[near], atol=1e-6)


def test_distorted_pinhole_bounds_are_the_undistorted_corners() -> None:
    min_u, max_u, min_v, max_v = EUROC.image_bounds()
    corners = EUROC.undistort_points(np.array([[0.0, 0.0], [752.0, 0.0], [0.0, 480.0], [752.0, 480.0]]))
    assert min_u == min(corners[0, 0], corners[2, 0]) and max_u == max(corners[1, 0], corners[3, 0])
    assert min_v == min(corners[0, 1], corners[1, 1]) and max_v == max(corners[2, 1], corners[3, 1])
    assert min_u < 0.0 and max_u > 752.0  # barrel distortion: the undistorted image is larger
    assert IDEAL.image_bounds() == (0.0, 640.0, 0.0, 480.0)
