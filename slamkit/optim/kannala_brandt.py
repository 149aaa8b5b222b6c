"""The Kannala-Brandt (equidistant fisheye) projection of optimization problems, one camera point at a time, for
the compiled optimizers (numba, ``nogil``): tracking's motion-only BA and the SciPy backend's kernels.

The model is slamkit/problems.py's (ORB-SLAM3's KannalaBrandt8): with r = |(x, y)| and theta = atan2(r, z),
theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8) and s = theta_d / r (1 / z on the
optical axis), u = fx s x + cx, v = fy s y + cy. ``cam`` arrays hold (fx, fy, cx, cy, k1, k2, k3, k4).
The vectorised reference is ``slamkit.geometry.camera.KannalaBrandtCamera`` (``project_image`` and
``project_image_jacobian``); the tests hold these kernels to it.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]

#: Below r = AXIS_EPS * |z| a point counts as on the optical axis: the pinhole limit of the model.
AXIS_EPS = 1e-12


@numba.njit(cache=True, nogil=True, inline="always")
def _terms(x: float, y: float, z: float, cam: F64) -> tuple[float, float, float, float]:  # pragma: no cover
    """r, s = theta_d / r (1 / z on the axis), theta_d and d theta_d / d theta of a camera point."""
    r = np.sqrt(x * x + y * y)
    theta = np.arctan2(r, z)
    t2 = theta * theta
    k1, k2, k3, k4 = cam[4], cam[5], cam[6], cam[7]
    theta_d = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    dtheta_d = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
    s = 1.0 / z if r <= AXIS_EPS * abs(z) else theta_d / r
    return r, s, theta_d, dtheta_d


@numba.njit(cache=True, nogil=True, inline="always")
def kb_project(x: float, y: float, z: float, cam: F64) -> tuple[float, float]:  # pragma: no cover - numba
    """Raw fisheye pixel (u, v) of the camera point (x, y, z), px."""
    _, s, _, _ = _terms(x, y, z, cam)
    return cam[0] * s * x + cam[2], cam[1] * s * y + cam[3]


@numba.njit(cache=True, nogil=True, inline="always")
def kb_jacobian(x: float, y: float, z: float, cam: F64, A: F64) -> None:  # pragma: no cover - numba
    """A[:2, :3] = d (u, v) / d (x, y, z), px/m: with R^2 = r^2 + z^2, d s / d(x, y) = (x, y) a where
    a = theta_d' z / (r^2 R^2) - theta_d / r^3, and d s / d z = -theta_d' / R^2 (a = 0 on the axis)."""
    r, s, theta_d, dtheta_d = _terms(x, y, z, cam)
    R2 = r * r + z * z
    a = 0.0 if r <= AXIS_EPS * abs(z) else dtheta_d * z / (r * r * R2) - theta_d / (r * r * r)
    ds_dz = -dtheta_d / R2
    fx, fy = cam[0], cam[1]
    A[0, 0] = fx * (s + x * x * a)
    A[0, 1] = fx * x * y * a
    A[0, 2] = fx * x * ds_dz
    A[1, 0] = fy * x * y * a
    A[1, 1] = fy * (s + y * y * a)
    A[1, 2] = fy * y * ds_dz


@numba.njit(cache=True, nogil=True)
def kb_project_many(xyz_c: F64, cam: F64) -> tuple[F64, F64]:  # pragma: no cover - numba
    """(N, 3) camera points -> (uv (N, 2) px, A (N, 2, 3) Jacobians): the kernels over an array (for tests)."""
    n = xyz_c.shape[0]
    uv = np.empty((n, 2))
    A = np.empty((n, 2, 3))
    for i in range(n):
        uv[i, 0], uv[i, 1] = kb_project(xyz_c[i, 0], xyz_c[i, 1], xyz_c[i, 2], cam)
        kb_jacobian(xyz_c[i, 0], xyz_c[i, 1], xyz_c[i, 2], cam, A[i])
    return uv, A
