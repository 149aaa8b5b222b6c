"""A simulated IMU rigidly attached to the synthetic camera, exact up to the noise it is told to add.

The body (IMU) frame b is fixed to the camera by T_b_c (pose of the camera in the body frame). From the
camera trajectory's analytic derivatives the body's kinematics are exact:

    R_w_b = R_w_c R_c_b,  p_b = p_c + R_w_c t_c_b,
    a_b = a_c + R_w_c (alpha_c x t_c_b + omega_c x (omega_c x t_c_b)),  omega_b = R_b_c omega_c.

The accelerometer measures the specific force R_w_b^T (a_b - g_w), the gyroscope omega_b, each plus a bias
(a random walk) and white noise, with continuous-time densities as in Kalibr/EuRoC sensor files:
discrete noise std = density / sqrt(dt), bias step std = random_walk * sqrt(dt).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slamkit.errors import ConfigError
from slamkit.io.synthetic.trajectory import CameraTrajectory
from slamkit.sensors import ImuSamples

F64 = NDArray[np.float64]

#: Gravity in the world frame of synthetic scenes (z up), m/s^2.
GRAVITY_W = np.array([0.0, 0.0, -9.81])


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time IMU noise densities. Defaults: EuRoC's ADIS16448 (its sensor.yaml).

    acc_noise_density: m/s^2/sqrt(Hz); gyro_noise_density: rad/s/sqrt(Hz);
    acc_random_walk: m/s^3/sqrt(Hz); gyro_random_walk: rad/s^2/sqrt(Hz). All 0 = a perfect IMU.
    """

    acc_noise_density: float = 2.0e-3
    gyro_noise_density: float = 1.6968e-4
    acc_random_walk: float = 3.0e-3
    gyro_random_walk: float = 1.9393e-5

    def __post_init__(self) -> None:
        for key in ("acc_noise_density", "gyro_noise_density", "acc_random_walk", "gyro_random_walk"):
            value = getattr(self, key)
            if not (isinstance(value, int | float) and np.isfinite(value) and value >= 0):
                raise ConfigError(f"dataset.imu_{key}: expected a number >= 0, got {value!r}")


@dataclass(frozen=True)
class BodyKinematics:
    """Exact IMU-body state at M times, world frame. R_w_b: (M, 3, 3); p_w, v_w (m/s), a_w (m/s^2): (M, 3);
    omega_b: (M, 3) rad/s, body angular velocity in the body frame."""

    R_w_b: F64
    p_w: F64
    v_w: F64
    a_w: F64
    omega_b: F64


def body_kinematics(trajectory: CameraTrajectory, T_b_c: F64, t_s: ArrayLike) -> BodyKinematics:
    """The body's exact state at times t_s (M,) for a camera following ``trajectory``; T_b_c: (4, 4)."""
    cam = trajectory.sample(t_s)
    R_b_c, t_b_c = T_b_c[:3, :3], T_b_c[:3, 3]
    R_c_b = R_b_c.T
    t_c_b = -R_c_b @ t_b_c  # body origin in the camera frame
    lever_w = cam.R_w_c @ t_c_b  # (M, 3)
    w, al = cam.omega_c, cam.alpha_c
    vel_c = np.cross(w, t_c_b)
    acc_c = np.cross(al, t_c_b) + np.cross(w, np.cross(w, t_c_b))
    return BodyKinematics(
        R_w_b=cam.R_w_c @ R_c_b,
        p_w=cam.p_w + lever_w,
        v_w=cam.v_w + np.einsum("mij,mj->mi", cam.R_w_c, vel_c),
        a_w=cam.a_w + np.einsum("mij,mj->mi", cam.R_w_c, acc_c),
        omega_b=w @ R_b_c.T,
    )


@dataclass(frozen=True)
class ImuStream:
    """A whole simulated IMU stream: the measurements and the true biases at each sample.

    samples: the measurements (t_s (N,), acc_mps2 (N, 3), gyro_radps (N, 3)), body frame.
    acc_bias, gyro_bias: (N, 3) the true biases added to each measurement (m/s^2, rad/s).
    """

    samples: ImuSamples
    acc_bias: F64
    gyro_bias: F64

    def between(self, t_after_s: float, t_until_s: float) -> ImuSamples:
        """Samples with t in (t_after_s, t_until_s]."""
        t = self.samples.t_s
        lo, hi = np.searchsorted(t, t_after_s, side="right"), np.searchsorted(t, t_until_s, side="right")
        return ImuSamples(t[lo:hi], self.samples.acc_mps2[lo:hi], self.samples.gyro_radps[lo:hi])


def simulate_imu(
    trajectory: CameraTrajectory,
    T_b_c: F64,
    rate_hz: float,
    duration_s: float,
    noise: ImuNoise,
    rng: np.random.Generator,
    acc_bias0: F64 | None = None,
    gyro_bias0: F64 | None = None,
) -> ImuStream:
    """Measurements at t_k = k / rate_hz, k = 0 .. floor(duration_s * rate_hz), with biases starting at
    acc_bias0 / gyro_bias0 ((3,), default 0) and drifting as random walks; noise from ``rng``."""
    if not rate_hz > 0:
        raise ConfigError(f"dataset.imu_rate_hz: expected a positive rate, got {rate_hz}")
    n = int(np.floor(duration_s * rate_hz + 1e-9)) + 1
    t = np.arange(n, dtype=np.float64) / rate_hz  # k / rate exactly as a double: aligns with frame times
    body = body_kinematics(trajectory, T_b_c, t)
    specific_force_b = np.einsum("mji,mj->mi", body.R_w_b, body.a_w - GRAVITY_W)
    dt = 1.0 / rate_hz
    ba0 = np.zeros(3) if acc_bias0 is None else np.asarray(acc_bias0, dtype=np.float64)
    bg0 = np.zeros(3) if gyro_bias0 is None else np.asarray(gyro_bias0, dtype=np.float64)
    # Draw every stream in a fixed order so the result depends on the seed alone.
    steps_a = rng.standard_normal((n, 3)) * noise.acc_random_walk * np.sqrt(dt)
    steps_g = rng.standard_normal((n, 3)) * noise.gyro_random_walk * np.sqrt(dt)
    white_a = rng.standard_normal((n, 3)) * noise.acc_noise_density / np.sqrt(dt)
    white_g = rng.standard_normal((n, 3)) * noise.gyro_noise_density / np.sqrt(dt)
    steps_a[0] = steps_g[0] = 0.0
    acc_bias = ba0 + np.cumsum(steps_a, axis=0)
    gyro_bias = bg0 + np.cumsum(steps_g, axis=0)
    samples = ImuSamples(t, specific_force_b + acc_bias + white_a, body.omega_b + gyro_bias + white_g)
    return ImuStream(samples, acc_bias, gyro_bias)
