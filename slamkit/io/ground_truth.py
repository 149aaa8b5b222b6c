"""Ground truth for dataset frames: re-anchor the poses of a ground-truth trajectory to the camera and
interpolate them at the frame times (the file itself is read by ``slamkit.io.trajectory_io``)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from slamkit.sensors import F64, Trajectory


def transform_trajectory(traj: Trajectory, T_b_c: F64) -> Trajectory:
    """Right-multiply every pose: T_w_b -> T_w_c = T_w_b @ T_b_c (e.g. body poses to camera poses).

    T_b_c: (4, 4) float64, the camera in the frame the trajectory's poses describe.
    """
    return Trajectory(traj.t_s.copy(), traj.T_w_c @ T_b_c[None, :, :])


def poses_at(traj: Trajectory, t_query: F64, max_gap_s: float) -> list[F64 | None]:
    """Ground-truth pose (4, 4) T_w_c at each query time (M,) s, interpolated between the samples that bracket it.

    Translation is linear and rotation SLERP between samples t0 < t < t1, used only when
    t1 - t0 <= ``max_gap_s`` (a wider gap is a tracking dropout: no ground truth there). A query equal
    to a sample time returns that sample (the first of repeated stamps). Queries outside
    [t_first, t_last] get None. traj.t_s must be non-decreasing (as the trajectory readers guarantee).
    """
    out: list[F64 | None] = [None] * int(t_query.shape[0])
    n = len(traj)
    if n == 0:
        return out
    t = traj.t_s
    rots = Rotation.from_matrix(traj.T_w_c[:, :3, :3])
    for k, tq in enumerate(t_query):
        j = int(np.searchsorted(t, tq, side="left"))
        if j < n and t[j] == tq:
            out[k] = traj.T_w_c[j].copy()
            continue
        if j == 0 or j == n:
            continue
        t0, t1 = t[j - 1], t[j]  # t0 < tq < t1, so t1 > t0 even with repeated stamps
        if t1 - t0 > max_gap_s:
            continue
        a = (tq - t0) / (t1 - t0)
        T = np.eye(4)
        T[:3, :3] = Slerp([t0, t1], rots[j - 1 : j + 1])([tq]).as_matrix()[0]
        T[:3, 3] = (1.0 - a) * traj.T_w_c[j - 1, :3, 3] + a * traj.T_w_c[j, :3, 3]
        out[k] = T
    return out
