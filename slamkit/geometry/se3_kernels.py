"""Compiled (numba) SE(3) kernels shared by the solvers' inner loops.

``se3_exp_times`` is the left-perturbation retraction T <- exp(xi) T of both Levenberg-Marquardt loops that
update poses inside compiled code: tracking's motion-only bundle adjustment (slamkit.pipeline.pose_optimization)
and the scipy backend's bundle adjustment (slamkit_scipy.kernels.ba_retract). The vectorised NumPy maps of the
same exponential are slamkit.geometry.se3.SE3.exp and slamkit_scipy.lie.se3_exp_batch (the tests compare them).
numba compiles se3_exp_times into its callers' caches, and a caller's cache is invalidated only by its own file
(numba's documented limitation, numba/numba#1833): after changing this file, touch or clear the caches of
slamkit/pipeline/pose_optimization.py and plugins/slamkit_scipy/kernels.py.
"""

from __future__ import annotations

import numba
import numpy as np

from slamkit.geometry._checks import F64
from slamkit.geometry.so3 import _SMALL_ANGLE

__all__ = ["se3_exp_times"]


@numba.njit(cache=True, nogil=True)
def se3_exp_times(xi: F64, T: F64) -> F64:  # pragma: no cover - numba
    """exp(xi) @ T: xi (6,) twist [omega (rad), v (m)] (rotation first, slamkit.geometry.se3's order), T (4, 4)
    a rigid transform T_a_b -> new (4, 4) array (the inputs are not written).

    Left perturbation (g2o's VertexSE3Expmap / ORB-SLAM's pose updates): xi is expressed in frame a, the frame
    T maps into (the camera frame for T = T_c_w), so the result maps frame b into the perturbed frame a.
    exp(xi) = [[I + a W + b W^2, (I + b W + c W^2) v], [0, 1]] with W = hat(omega) (W x = omega x x),
    theta = |omega|, a = sin(theta) / theta, b = (1 - cos theta) / theta^2, c = (theta - sin theta) / theta^3:
    Rodrigues' rotation and the SO(3) left Jacobian J_l(omega) applied to v (the true group exponential, not
    the [exp(omega), v] split). Below slamkit.geometry.so3's _SMALL_ANGLE (1e-4 rad) a, b, c are their Taylor
    series to theta^4 (truncation < theta^6 / 5040 < 1e-27; the closed forms would divide by ~0), from it on the
    closed forms. Accuracy (tests/unit/geometry/test_se3_kernels.py, against scipy's expm): the rotation block to a
    few ulps; the translation to a few ulps of |v| with the series, but with the closed forms b's 1 - cos theta
    cancels (cos rounded to ~eps) and b W v errs by up to ~eps |v| / (2 theta): ~1e-12 |v| just above the switch,
    ~1e-13 |v| at 1e-3 rad (harmless for a retraction step; kept for the bits, see docs/BENCHMARKS.md expkernel).

    Evaluation order (fixed, the results of both solvers depend on it bit for bit): theta^2 = w0^2 + w1^2 + w2^2,
    b and c divide by theta^2 (not theta * theta); W^2 = W @ W and the product exp(xi) @ T are matrix products
    (numba's BLAS calls); the rotation block is I + (a W + b W^2) and the translation v_i + sum_j (b W + c W^2)_ij v_j,
    summed over j = 0, 1, 2 in order."""
    wx, wy, wz = xi[0], xi[1], xi[2]
    t2 = wx * wx + wy * wy + wz * wz
    theta = np.sqrt(t2)
    if theta < _SMALL_ANGLE:
        a = 1.0 - t2 / 6.0 + t2 * t2 / 120.0
        b = 0.5 - t2 / 24.0 + t2 * t2 / 720.0
        c = 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0
    else:
        a = np.sin(theta) / theta
        b = (1.0 - np.cos(theta)) / t2
        c = (theta - np.sin(theta)) / (t2 * theta)
    W = np.zeros((3, 3))
    W[0, 1], W[0, 2] = -wz, wy
    W[1, 0], W[1, 2] = wz, -wx
    W[2, 0], W[2, 1] = -wy, wx
    W2 = W @ W
    E = np.eye(4)
    for i in range(3):
        for j in range(3):
            E[i, j] += a * W[i, j] + b * W2[i, j]
        s = xi[3 + i]
        for j in range(3):
            s += (b * W[i, j] + c * W2[i, j]) * xi[3 + j]
        E[i, 3] = s
    out: F64 = E @ T
    return out
