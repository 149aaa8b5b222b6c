"""Conversions between slamkit's arrays and GTSAM's types (the plugin's boundary).

slamkit keyframes carry T_c_w; GTSAM's projection factors want the camera's pose in the world, T_w_c. slamkit's
Sim3 acts as x' = s R x + t and is stored [[s R, t], [0, 1]]; GTSAM's Similarity3 acts as s (R x + t') and its
matrix is [[R, t'], [0, 1/s]] = ours / s, so t' = t / s. Both groups have the same tangent [omega, v, lambda]
(GTSAM's matrix is ours times the scalar 1/s, so their logarithms differ by lambda I only in the corner).
"""

from __future__ import annotations

import gtsam
import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


def pose3_from_T(T: F64) -> gtsam.Pose3:
    """(4, 4) rigid matrix -> gtsam.Pose3 (the same transform)."""
    return gtsam.Pose3(np.ascontiguousarray(T, dtype=np.float64))


def similarity3_from_S(S: F64) -> gtsam.Similarity3:
    """(4, 4) slamkit Sim3 [[s R, t], [0, 1]] -> the same transform as a gtsam.Similarity3."""
    A = S[:3, :3]
    s = float(np.cbrt(np.linalg.det(A)))
    return gtsam.Similarity3(gtsam.Rot3(A / s), S[:3, 3] / s, s)


def S_from_similarity3(g: gtsam.Similarity3) -> F64:
    """gtsam.Similarity3 -> (4, 4) slamkit Sim3 [[s R, t], [0, 1]] (GTSAM's matrix times s)."""
    M = np.asarray(g.matrix(), dtype=np.float64)
    out: F64 = M / M[3, 3]
    return out


def poses_from_extract(rows: F64) -> F64:
    """gtsam.utilities.extractPose3 rows (K, 12) = [R row-major (9), t (3)] -> (K, 4, 4) matrices."""
    K = len(rows)
    T = np.tile(np.eye(4), (K, 1, 1))
    T[:, :3, :3] = rows[:, :9].reshape(K, 3, 3)
    T[:, :3, 3] = rows[:, 9:12]
    return T


def invert_rigid(T: F64) -> F64:
    """(..., 4, 4) rigid transforms -> inverses [[R^T, -R^T t], [0, 1]]."""
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out
