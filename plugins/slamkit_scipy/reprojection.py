"""Vectorised pinhole (and rectified-stereo) or Kannala-Brandt reprojection residuals with analytic Jacobians.

Residual r = projection - observation, per observation a 3-vector (u, v, u_right); for a monocular
observation the third entry and its Jacobian row are 0, so mono and stereo share one array layout.
Projection of p = (x, y, z) in the camera frame: u = fx x/z + cx, v = fy y/z + cy, u_right = u - bf/z; for a
fisheye problem (``Observations.kb`` set) the Kannala-Brandt model of slamkit/problems.py, monocular only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slamkit.optim.costs import kannala_brandt_project
from slamkit_scipy.kernels import kb_jacobians

F64 = NDArray[np.float64]
B = NDArray[np.bool_]


@dataclass
class Observations:
    """E observations. uvr: (E, 3) px (u, v, u_right; u_right 0 where mono); stereo: (E,) bool;
    intr: (E, 4) fx fy cx cy; bf: (E,) m px; info: (E,) 1/sigma^2; delta: (E,) Huber threshold on the
    whitened norm; chi2_max: (E,) chi-square gate (mono or stereo); kb: (E, 4) k1..k4 of a Kannala-Brandt
    camera (observations are raw fisheye pixels), None for the pinhole model."""

    uvr: F64
    stereo: B
    intr: F64
    bf: F64
    info: F64
    delta: F64
    chi2_max: F64
    kb: F64 | None = None

    def subset(self, keep: NDArray[np.int64] | B) -> Observations:
        return Observations(
            self.uvr[keep],
            self.stereo[keep],
            self.intr[keep],
            self.bf[keep],
            self.info[keep],
            self.delta[keep],
            self.chi2_max[keep],
            None if self.kb is None else self.kb[keep],
        )

    def cam(self) -> F64:
        """(E, 8) fx, fy, cx, cy, k1..k4 per observation (k = 0 for the pinhole model): the compiled kernels' layout."""
        out = np.zeros((self.intr.shape[0], 8))
        out[:, :4] = self.intr
        if self.kb is not None:
            out[:, 4:] = self.kb
        return out


def make_observations(
    uv_px: F64,
    u_right_px: F64,
    intr: F64,
    bf: F64,
    info: F64,
    chi2_mono: float,
    chi2_stereo: float,
    kb: F64 | None = None,
) -> Observations:
    """Pack per-observation arrays (intr (E, 4), bf (E,) and kb (E, 4) already gathered per observation)."""
    stereo = np.isfinite(u_right_px)
    uvr = np.zeros((uv_px.shape[0], 3))
    uvr[:, :2] = uv_px
    uvr[stereo, 2] = u_right_px[stereo]
    chi2_max = np.where(stereo, chi2_stereo, chi2_mono)
    return Observations(uvr, stereo, intr, bf, info, np.sqrt(chi2_max), chi2_max, kb)


def residuals(p_c: F64, obs: Observations) -> F64:
    """p_c: (E, 3) m points in each observation's camera -> (E, 3) residuals px (0 third entry if mono)."""
    iz = 1.0 / p_c[:, 2]
    fx, fy, cx, cy = obs.intr.T
    r = np.empty_like(p_c)
    if obs.kb is None:
        r[:, 0] = fx * p_c[:, 0] * iz + cx
        r[:, 1] = fy * p_c[:, 1] * iz + cy
    else:
        r[:, 0], r[:, 1] = kannala_brandt_project(p_c, obs.intr, obs.kb)
    r[:, 2] = np.where(obs.stereo, r[:, 0] - obs.bf * iz, 0.0)
    r -= obs.uvr
    r[~obs.stereo, 2] = 0.0
    return r


def projection_jacobian(p_c: F64, obs: Observations) -> F64:
    """(E, 3, 3) d residual / d p_c (the third row is 0 for monocular observations)."""
    if obs.kb is not None:
        A = np.zeros((p_c.shape[0], 3, 3))
        A[:, :2, :] = _kb_rows(p_c, obs)
        return A
    x, y, z = p_c.T
    iz = 1.0 / z
    iz2 = iz * iz
    fx, fy = obs.intr[:, 0], obs.intr[:, 1]
    A = np.zeros((p_c.shape[0], 3, 3))
    A[:, 0, 0] = fx * iz
    A[:, 0, 2] = -fx * x * iz2
    A[:, 1, 1] = fy * iz
    A[:, 1, 2] = -fy * y * iz2
    st = obs.stereo
    A[st, 2, 0] = A[st, 0, 0]
    A[st, 2, 2] = (obs.bf[st] - fx[st] * x[st]) * iz2[st]
    return A


def _kb_rows(p_c: F64, obs: Observations) -> F64:
    """(E, 2, 3) d (u, v) / d p_c of Kannala-Brandt observations (the compiled kernel, per observation's camera)."""
    return kb_jacobians(np.ascontiguousarray(p_c), obs.cam())


def pose_jacobian(p_c: F64, A: F64) -> F64:
    """(E, 3, 6) d residual / d xi for the left perturbation T <- exp(xi) T, xi = [omega, v].

    d p_c / d omega = -hat(p_c), so row a of A gives a^T (-hat(p_c)) = cross(p_c, a); d p_c / d v = I.
    """
    J = np.empty((A.shape[0], 3, 6))
    J[:, :, :3] = np.cross(p_c[:, None, :], A)
    J[:, :, 3:] = A
    return J


def chi2_of(r: F64, obs: Observations) -> F64:
    """(E,) r^T Omega r with Omega = info I."""
    out: F64 = obs.info * np.einsum("ij,ij->i", r, r)
    return out
