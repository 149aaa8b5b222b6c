"""Camera paths: interpolation, C2 continuity, exact derivatives, roll-free orientation, and loops."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from slamkit.errors import ConfigError
from slamkit.geometry.so3 import so3_log
from slamkit.io.synthetic import SCENES, SyntheticDataset
from slamkit.io.synthetic.trajectory import PeriodicBSpline


def test_spline_passes_through_waypoints_and_is_periodic() -> None:
    rng = np.random.default_rng(0)
    pts = rng.uniform(-3, 3, (9, 3))
    spline = PeriodicBSpline(pts, period_s=18.0)
    t = np.arange(9) * 2.0
    np.testing.assert_allclose(spline.evaluate(t), pts, atol=1e-12)
    tt = rng.uniform(0, 18, 20)
    for order in range(3):
        np.testing.assert_allclose(spline.evaluate(tt + 18.0, order), spline.evaluate(tt, order), atol=1e-9)


def test_spline_is_c2_across_knots_with_a_jerk_jump() -> None:
    rng = np.random.default_rng(1)
    spline = PeriodicBSpline(rng.uniform(-3, 3, (7, 3)), period_s=7.0)
    eps = 1e-9
    knots = np.arange(7, dtype=np.float64)[1:]
    for order in range(3):
        np.testing.assert_allclose(spline.evaluate(knots - eps, order), spline.evaluate(knots + eps, order), atol=1e-6)
    # The third derivative jumps: cubic, not smoother (so the test above could fail).
    jump = np.abs(spline.evaluate(knots - eps, 3) - spline.evaluate(knots + eps, 3)).max()
    assert jump > 1e-2


def test_spline_rejects_too_few_waypoints() -> None:
    with pytest.raises(ConfigError, match="at least 4 waypoints"):
        PeriodicBSpline(np.zeros((3, 3)), 1.0)


@pytest.mark.parametrize("scene", sorted(SCENES))
def test_analytic_derivatives_match_finite_differences(synthetic: Callable[..., SyntheticDataset], scene: str) -> None:
    traj = synthetic(scene=scene).trajectory
    h = 1e-5
    # Central differences straddling a knot err by ~h * (jump of the next derivative): atol a few 1e-5.
    for t in np.linspace(0.3, traj.period_s - 0.3, 7):
        s = traj.sample(np.array([t - h, t, t + h]))
        np.testing.assert_allclose((s.p_w[2] - s.p_w[0]) / (2 * h), s.v_w[1], atol=1e-6)
        np.testing.assert_allclose((s.v_w[2] - s.v_w[0]) / (2 * h), s.a_w[1], atol=3e-5)
        W = s.R_w_c[1].T @ (s.R_w_c[2] - s.R_w_c[0]) / (2 * h)  # = [omega_c]x
        np.testing.assert_allclose([W[2, 1], W[0, 2], W[1, 0]], s.omega_c[1], atol=1e-6)
        np.testing.assert_allclose((s.omega_c[2] - s.omega_c[0]) / (2 * h), s.alpha_c[1], atol=3e-5)


@pytest.mark.parametrize("scene", sorted(SCENES))
def test_poses_are_rotations_without_roll_and_motion_is_moderate(
    synthetic: Callable[..., SyntheticDataset], scene: str
) -> None:
    ds = synthetic(scene=scene)
    T = ds.ground_truth.T_w_c
    R = T[:, :3, :3]
    np.testing.assert_allclose(R.transpose(0, 2, 1) @ R, np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_allclose(R[:, 2, 0], 0.0, atol=1e-12)  # camera x axis stays horizontal: no roll
    s = ds.trajectory.sample(ds.frame_times_s)
    # Trackable motion at 30 Hz: under ~1 m/s and ~1 rad/s.
    assert np.linalg.norm(s.v_w, axis=1).max() < 1.2
    assert np.linalg.norm(s.omega_c, axis=1).max() < 1.0


@pytest.mark.parametrize("scene", sorted(SCENES))
def test_trajectory_returns_to_an_earlier_place_with_a_similar_view(
    synthetic: Callable[..., SyntheticDataset], scene: str
) -> None:
    ds = synthetic(scene=scene)
    T = ds.ground_truth.T_w_c
    t = ds.ground_truth.t_s
    p = T[:, :3, 3]
    later = np.nonzero(t > t[0] + 10.0)[0]
    found = []
    for j in later[::3]:
        earlier = np.nonzero(t < t[j] - 10.0)[0]  # at least 10 s apart: a loop, not a pause
        d = np.linalg.norm(p[earlier] - p[j], axis=1)
        i = earlier[np.argmin(d)]
        angle = np.linalg.norm(so3_log(T[i, :3, :3].T @ T[j, :3, :3]))
        if d.min() < 0.1 and angle < np.radians(5):
            found.append((i, j))
    assert found, f"{scene}: the camera never comes back to a place it saw"
    # And between the two visits it went far away (a real loop).
    i, j = found[0]
    assert np.linalg.norm(p[i : j + 1] - p[i], axis=1).max() > 2.0
