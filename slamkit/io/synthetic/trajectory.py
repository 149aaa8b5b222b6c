"""Smooth closed camera trajectories with analytic derivatives (the source of exact ground truth and IMU).

Position: a periodic uniform cubic B-spline whose control points are solved so that it passes through the
waypoints (C2: position, velocity and acceleration are continuous; jerk is piecewise constant).
Orientation: the camera looks along a forward vector f(t) (towards a look-at target spline, or towards its
own position a little later), with yaw psi = atan2(f_y, f_x) and pitch theta = atan2(f_z, |f_xy|) and no
roll. Both angles and their first two time derivatives follow analytically from f, f', f''; so do the
angular velocity and angular acceleration.

Frames: world z up; camera x right, y down, z forward (docs/conventions.md). R_w_c's columns are the
camera's right, down and forward axes in the world:
right = (sin psi, -cos psi, 0), forward = (cos theta cos psi, cos theta sin psi, sin theta), down = forward x right.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slamkit.errors import ConfigError

F64 = NDArray[np.float64]

# Uniform cubic B-spline basis: C(u) = [1, u, u^2, u^3] @ _M @ [P_{i-1}, P_i, P_{i+1}, P_{i+2}], u in [0, 1).
_M = np.array([[1, 4, 1, 0], [-3, 0, 3, 0], [3, -6, 3, 0], [-1, 3, -3, 1]], dtype=np.float64) / 6.0


class PeriodicBSpline:
    """Closed C2 curve through ``points`` (N, D) at times k * period_s / N, repeating with ``period_s``.

    ``evaluate(t_s, order)`` gives the ``order``-th time derivative (0..3) at times t_s (M,) -> (M, D).
    """

    def __init__(self, points: F64, period_s: float) -> None:
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[0] < 4:
            raise ConfigError(f"a closed spline needs at least 4 waypoints as (N, D); got shape {pts.shape}")
        if not period_s > 0:
            raise ConfigError(f"spline period must be positive, got {period_s}")
        n = pts.shape[0]
        # Interpolation: C(k) = (P_{k-1} + 4 P_k + P_{k+1}) / 6 = W_k, a circulant system (diagonally dominant).
        A = np.zeros((n, n))
        for k in range(n):
            A[k, (k - 1) % n], A[k, k], A[k, (k + 1) % n] = 1 / 6, 4 / 6, 1 / 6
        self.control = np.linalg.solve(A, pts)
        self.n = n
        self.period_s = float(period_s)

    def evaluate(self, t_s: ArrayLike, order: int = 0) -> F64:
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        s = np.mod(t / self.period_s, 1.0) * self.n  # spline parameter in [0, n)
        seg = np.minimum(np.floor(s).astype(np.int64), self.n - 1)
        u = s - seg
        zeros, ones = np.zeros_like(u), np.ones_like(u)
        if order == 0:
            U = np.stack([ones, u, u * u, u**3], axis=1)
        elif order == 1:
            U = np.stack([zeros, ones, 2 * u, 3 * u * u], axis=1)
        elif order == 2:
            U = np.stack([zeros, zeros, 2 * ones, 6 * u], axis=1)
        elif order == 3:
            U = np.stack([zeros, zeros, zeros, 6 * ones], axis=1)
        else:
            raise ValueError(f"derivative order must be 0..3, got {order}")
        idx = (seg[:, None] + np.arange(-1, 3)[None, :]) % self.n  # (M, 4) control point indices
        weights = U @ _M  # (M, 4)
        ds_dt = self.n / self.period_s
        out: F64 = np.einsum("mk,mkd->md", weights, self.control[idx]) * ds_dt**order
        return out


@dataclass(frozen=True)
class TrajectorySample:
    """Camera state at M times (world frame, z up). All float64.

    t_s: (M,) s. p_w: (M, 3) camera centre, m. v_w, a_w: (M, 3) its velocity (m/s) and acceleration (m/s^2).
    R_w_c: (M, 3, 3) camera orientation. omega_c: (M, 3) rad/s, angular velocity of the camera in the
    camera frame (R_w_c' = R_w_c [omega_c]x). alpha_c: (M, 3) rad/s^2, its time derivative (camera frame).
    """

    t_s: F64
    p_w: F64
    v_w: F64
    a_w: F64
    R_w_c: F64
    omega_c: F64
    alpha_c: F64

    @property
    def T_w_c(self) -> F64:
        """(M, 4, 4) camera poses in the world."""
        T = np.tile(np.eye(4), (self.t_s.shape[0], 1, 1))
        T[:, :3, :3] = self.R_w_c
        T[:, :3, 3] = self.p_w
        return T


def _yaw_pitch_derivatives(f: F64, df: F64, ddf: F64) -> tuple[F64, F64, F64, F64, F64, F64]:
    """Yaw/pitch of forward vectors f (M, 3) and their first and second time derivatives, rad (/s, /s^2)."""
    fx, fy, fz = f.T
    dfx, dfy, dfz = df.T
    ddfx, ddfy, ddfz = ddf.T
    h2 = fx * fx + fy * fy
    if np.any(h2 < 1e-12):
        raise ConfigError("synthetic camera path looks straight up or down (yaw undefined): fix the scene")
    h = np.sqrt(h2)
    psi = np.arctan2(fy, fx)
    cross = fx * dfy - fy * dfx
    dot = fx * dfx + fy * dfy
    dpsi = cross / h2
    ddpsi = (fx * ddfy - fy * ddfx) / h2 - cross * 2 * dot / (h2 * h2)
    theta = np.arctan2(fz, h)
    dh = dot / h
    ddh = (dfx * dfx + dfy * dfy + fx * ddfx + fy * ddfy - dh * dh) / h
    num = h * dfz - fz * dh
    den = h2 + fz * fz
    dtheta = num / den
    dnum = h * ddfz - fz * ddh
    dden = 2 * (fx * dfx + fy * dfy + fz * dfz)
    ddtheta = (dnum * den - num * dden) / (den * den)
    return psi, dpsi, ddpsi, theta, dtheta, ddtheta


def rotation_from_yaw_pitch(psi: F64, theta: F64) -> F64:
    """(M,) yaw, pitch (rad) -> (M, 3, 3) R_w_c of a roll-free camera (x right, y down, z forward; world z up)."""
    cp, sp, ct, st = np.cos(psi), np.sin(psi), np.cos(theta), np.sin(theta)
    right = np.stack([sp, -cp, np.zeros_like(sp)], axis=1)
    down = np.stack([st * cp, st * sp, -ct], axis=1)
    forward = np.stack([ct * cp, ct * sp, st], axis=1)
    return np.stack([right, down, forward], axis=2)


class CameraTrajectory:
    """The camera's closed path: a position spline and a forward-vector rule (look-at or look-ahead).

    position: spline of camera centres (m, world). look_at: spline of look-at targets (m, world), or None to
    look ahead at the camera's own position ``look_ahead_s`` later, turned by ``yaw_offset_rad`` about z.
    """

    def __init__(
        self,
        position: PeriodicBSpline,
        look_at: PeriodicBSpline | None = None,
        look_ahead_s: float = 1.0,
        yaw_offset_rad: float = 0.0,
    ) -> None:
        self.position = position
        self.look_at = look_at
        self.look_ahead_s = float(look_ahead_s)
        c, s = np.cos(yaw_offset_rad), np.sin(yaw_offset_rad)
        self._R_offset = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    @property
    def period_s(self) -> float:
        return self.position.period_s

    def _forward(self, t: F64, p: tuple[F64, F64, F64]) -> tuple[F64, F64, F64]:
        """Forward vector f and its first two derivatives at times t, each (M, 3) (not unit length)."""
        if self.look_at is not None:
            q = [self.look_at.evaluate(t, k) for k in range(3)]
            return q[0] - p[0], q[1] - p[1], q[2] - p[2]
        ahead = [self.position.evaluate(t + self.look_ahead_s, k) for k in range(3)]
        R = self._R_offset
        return (ahead[0] - p[0]) @ R.T, (ahead[1] - p[1]) @ R.T, (ahead[2] - p[2]) @ R.T

    def sample(self, t_s: ArrayLike) -> TrajectorySample:
        """The exact camera state at times t_s (M,) s."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        p = (self.position.evaluate(t, 0), self.position.evaluate(t, 1), self.position.evaluate(t, 2))
        f, df, ddf = self._forward(t, p)
        psi, dpsi, ddpsi, theta, dtheta, ddtheta = _yaw_pitch_derivatives(f, df, ddf)
        R_w_c = rotation_from_yaw_pitch(psi, theta)
        cp, sp = np.cos(psi), np.sin(psi)
        zeros = np.zeros_like(psi)
        e_z = np.stack([zeros, zeros, zeros + 1.0], axis=1)
        right = np.stack([sp, -cp, zeros], axis=1)  # the pitch axis (pitching up turns forward towards up)
        d_right = np.stack([cp, sp, zeros], axis=1) * dpsi[:, None]
        # omega_w = psi' e_z + theta' right ; its derivative adds theta' right'.
        omega_w = dpsi[:, None] * e_z + dtheta[:, None] * right
        alpha_w = ddpsi[:, None] * e_z + ddtheta[:, None] * right + dtheta[:, None] * d_right
        # In the camera frame: omega_c = R^T omega_w; and d/dt(R^T omega_w) = R^T alpha_w (the extra term
        # -[omega_c]x R^T omega_w = -omega_c x omega_c vanishes).
        omega_c = np.einsum("mji,mj->mi", R_w_c, omega_w)
        alpha_c = np.einsum("mji,mj->mi", R_w_c, alpha_w)
        return TrajectorySample(t, p[0], p[1], p[2], R_w_c, omega_c, alpha_c)

    def T_w_c(self, t_s: ArrayLike) -> F64:
        """(M, 4, 4) camera poses at times t_s (M,)."""
        return self.sample(t_s).T_w_c
