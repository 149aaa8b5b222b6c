"""The Kannala-Brandt projection of optimization problems (the compiled per-point kernels of tracking's motion-only
BA and the SciPy backend, the vectorised one of slamkit.optim.costs, the SciPy backend's Jacobian rows) against the
camera model the pipeline projects with (slamkit.geometry.camera.KannalaBrandtCamera)."""

from __future__ import annotations

import numpy as np
from slamkit_scipy.reprojection import make_observations, projection_jacobian, residuals

from slamkit.geometry import KannalaBrandtCamera
from slamkit.optim.costs import kannala_brandt_project
from slamkit.optim.kannala_brandt import kb_project_many

CAMERA = KannalaBrandtCamera(640, 480, 300.0, 310.0, 330.0, 235.0, [0.08, -0.02, 0.004, -0.0003])


def camera_points(n: int = 400) -> np.ndarray:
    rng = np.random.default_rng(5)
    theta = np.radians(85.0) * np.sqrt(rng.uniform(0.0, 1.0, n))
    phi = rng.uniform(-np.pi, np.pi, n)
    d = rng.uniform(0.5, 8.0, n)
    pts = np.stack([d * np.sin(theta) * np.cos(phi), d * np.sin(theta) * np.sin(phi), d * np.cos(theta)], axis=1)
    pts[0] = [0.0, 0.0, 2.0]  # on the optical axis
    return pts


def cam_array() -> np.ndarray:
    return np.r_[CAMERA.fx, CAMERA.fy, CAMERA.cx, CAMERA.cy, CAMERA.k]


def test_compiled_kernels_match_the_camera() -> None:
    xyz = camera_points()
    uv, A = kb_project_many(xyz, cam_array())
    ref_uv, valid = CAMERA.project_image(xyz)
    assert valid.all()
    np.testing.assert_allclose(uv, ref_uv, rtol=0, atol=1e-9)
    np.testing.assert_allclose(A, CAMERA.project_image_jacobian(xyz), rtol=1e-10, atol=1e-9)


def test_vectorised_projection_matches_the_camera() -> None:
    xyz = camera_points()
    n = len(xyz)
    u, v = kannala_brandt_project(xyz, np.tile(cam_array()[:4], (n, 1)), np.tile(CAMERA.k, (n, 1)))
    np.testing.assert_allclose(np.stack([u, v], axis=1), CAMERA.project_image(xyz)[0], rtol=0, atol=1e-9)


def test_scipy_residuals_and_jacobian_rows() -> None:
    xyz = camera_points()
    n = len(xyz)
    uv_obs = CAMERA.project_image(xyz)[0] + 0.5
    obs = make_observations(
        uv_obs,
        np.full(n, np.nan),
        np.tile(cam_array()[:4], (n, 1)),
        np.zeros(n),
        np.ones(n),
        5.991,
        7.815,
        np.tile(CAMERA.k, (n, 1)),
    )
    r = residuals(xyz, obs)
    np.testing.assert_allclose(r[:, :2], -0.5, atol=1e-9)
    assert np.all(r[:, 2] == 0.0)
    A = projection_jacobian(xyz, obs)
    np.testing.assert_allclose(A[:, :2], CAMERA.project_image_jacobian(xyz), rtol=1e-10, atol=1e-9)
    assert np.all(A[:, 2] == 0.0)
