"""The simulated IMU agrees with the trajectory: integration, gravity at rest, noise levels, per-frame windows."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from slamkit.geometry.so3 import so3_exp, so3_log
from slamkit.io.synthetic import SyntheticDataset
from slamkit.io.synthetic.dataset import DEFAULT_T_B_C
from slamkit.io.synthetic.imu import GRAVITY_W, ImuNoise, simulate_imu
from slamkit.io.synthetic.trajectory import CameraTrajectory, PeriodicBSpline

NOISE_FREE_IMU: dict[str, Any] = {
    "imu_acc_noise_density": 0.0,
    "imu_gyro_noise_density": 0.0,
    "imu_acc_random_walk": 0.0,
    "imu_gyro_random_walk": 0.0,
}


def _integrate(ds: SyntheticDataset, t0: float, t1: float) -> tuple[float, float, float]:
    """Integrate the IMU from the true body state at t0 to t1; errors (rad, m/s, m) against the truth."""
    assert ds.imu_stream is not None
    imu = ds.imu_stream.samples
    k0, k1 = np.searchsorted(imu.t_s, [t0, t1])
    truth = ds.body_state(np.array([imu.t_s[k0], imu.t_s[k1]]))
    R, v, p = truth.R_w_b[0], truth.v_w[0], truth.p_w[0]
    for k in range(k0, k1):
        dt = imu.t_s[k + 1] - imu.t_s[k]
        R1 = R @ so3_exp(0.5 * (imu.gyro_radps[k] + imu.gyro_radps[k + 1]) * dt)
        a0 = R @ imu.acc_mps2[k] + GRAVITY_W
        a1 = R1 @ imu.acc_mps2[k + 1] + GRAVITY_W
        p = p + v * dt + (2 * a0 + a1) / 6 * dt * dt
        v = v + 0.5 * (a0 + a1) * dt
        R = R1
    rot = float(np.linalg.norm(so3_log(truth.R_w_b[1].T @ R)))
    return rot, float(np.linalg.norm(v - truth.v_w[1])), float(np.linalg.norm(p - truth.p_w[1]))


@pytest.mark.parametrize(("scene", "t0"), [("room", 2.0), ("room", 17.0), ("planar", 5.0), ("long_loop", 30.0)])
def test_integrating_noise_free_imu_reproduces_the_pose_and_velocity_change(
    synthetic: Callable[..., SyntheticDataset], scene: str, t0: float
) -> None:
    ds = synthetic(scene=scene, **NOISE_FREE_IMU)
    rot, vel, pos = _integrate(ds, t0, t0 + 3.0)
    # Second-order integration at 200 Hz of a smooth path: errors of 1e-7..1e-6 (measured).
    assert rot < 1e-5 and vel < 1e-4 and pos < 1e-4


def test_biased_imu_does_not_reproduce_the_motion(synthetic: Callable[..., SyntheticDataset]) -> None:
    """The integration check above can fail: a default-noise IMU drifts visibly over 3 s."""
    ds = synthetic(scene="room")
    _, vel, pos = _integrate(ds, 2.0, 5.0)
    assert pos > 1e-3 or vel > 1e-3


def test_gravity_appears_in_the_accelerometer_at_rest() -> None:
    still = PeriodicBSpline(np.tile([1.0, 2.0, 1.5], (5, 1)), period_s=5.0)
    target = PeriodicBSpline(np.tile([4.0, 2.0, 1.5], (5, 1)), period_s=5.0)  # looking along +x, level
    traj = CameraTrajectory(still, target)
    stream = simulate_imu(traj, DEFAULT_T_B_C, 200.0, 2.0, ImuNoise(0, 0, 0, 0), np.random.default_rng(0))
    # DEFAULT_T_B_C's body is x forward, y left, z up: a level camera at rest feels +9.81 along body z.
    np.testing.assert_allclose(stream.samples.acc_mps2, np.tile([0.0, 0.0, 9.81], (401, 1)), atol=1e-12)
    np.testing.assert_allclose(stream.samples.gyro_radps, 0.0, atol=1e-12)


def test_noise_and_bias_follow_the_configured_densities() -> None:
    ds = SyntheticDataset(scene="room", imu_acc_noise_density=0.02, imu_gyro_random_walk=1e-3)
    exact = SyntheticDataset(scene="room", **NOISE_FREE_IMU)
    assert ds.imu_stream is not None and exact.imu_stream is not None
    dt = 1.0 / 200.0
    white_acc = ds.imu_stream.samples.acc_mps2 - exact.imu_stream.samples.acc_mps2 - ds.imu_stream.acc_bias
    np.testing.assert_allclose(white_acc.std(axis=0), 0.02 / np.sqrt(dt), rtol=0.05)
    steps = np.diff(ds.imu_stream.gyro_bias, axis=0)
    np.testing.assert_allclose(steps.std(axis=0), 1e-3 * np.sqrt(dt), rtol=0.05)
    # The gyro measurement is truth + bias + its own white noise (default density).
    white_gyro = ds.imu_stream.samples.gyro_radps - exact.imu_stream.samples.gyro_radps - ds.imu_stream.gyro_bias
    np.testing.assert_allclose(white_gyro.std(axis=0), 1.6968e-4 / np.sqrt(dt), rtol=0.05)


def test_frames_carry_each_imu_sample_once_even_across_a_skip(synthetic: Callable[..., SyntheticDataset]) -> None:
    ds = synthetic(scene="room", skip=[10, 40], max_frames=60)
    assert ds.imu_stream is not None
    prev_t = -np.inf
    chunks = []
    for frame in ds:
        t = frame.imu.t_s
        assert np.all(t > prev_t) and np.all(t <= frame.timestamp_s)
        assert len(t) == 0 or t[-1] == frame.timestamp_s or frame.timestamp_s - t[-1] < 1 / 200
        chunks.append(t)
        prev_t = frame.timestamp_s
    got = np.concatenate(chunks)
    all_t = ds.imu_stream.samples.t_s
    np.testing.assert_array_equal(got, all_t[all_t <= prev_t])
    # The first frame after the skip (raw 41, after raw 9) carries the whole gap: samples k / 200 in
    # (9 / 30, 41 / 30], i.e. k = 61 .. 273.
    assert ds.raw_indices()[10] == 41
    np.testing.assert_array_equal(ds[10].imu.t_s, np.arange(61, 274) / 200.0)
