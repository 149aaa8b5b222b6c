"""Ground-truth trajectory files: TUM (``t x y z qx qy qz qw``), EuRoC CSV, KITTI 3x4 pose rows.

Quaternions exist only here, at the file boundary; in memory poses are (4, 4) float64 matrices.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation, Slerp

from slamkit.errors import DatasetError
from slamkit.io.textfiles import (
    check_columns,
    check_increasing,
    ns_to_s,
    parse_float,
    parse_int,
    read_numeric_table,
    read_rows,
)
from slamkit.sensors import Trajectory

F64 = NDArray[np.float64]

#: |‖q‖ - 1| above this means the line is not a rotation (files round quaternions to ~4 decimals).
QUAT_NORM_TOL = 1e-2


def _poses_from_quat(path: Path, lines: NDArray[np.int64], xyz: F64, q_xyzw: F64) -> F64:
    norms = np.linalg.norm(q_xyzw, axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > QUAT_NORM_TOL)
    if bad.size:
        i = int(bad[0])
        raise DatasetError(f"{path}:{int(lines[i])}: quaternion norm is {norms[i]:.4f}; expected a unit quaternion")
    T = np.tile(np.eye(4), (xyz.shape[0], 1, 1))
    if xyz.shape[0]:
        T[:, :3, :3] = Rotation.from_quat(q_xyzw).as_matrix()  # scalar-last, normalises
        T[:, :3, 3] = xyz
    return T


def read_tum_trajectory(path: Path) -> Trajectory:
    """Read a TUM trajectory file: ``timestamp tx ty tz qx qy qz qw`` per line (s, m, Hamilton quaternion).

    Returns the poses as written (TUM ground truth: T_w_c of the colour camera's optical frame).
    Raises DatasetError naming file and line for a wrong column count, a non-number, a non-unit
    quaternion, or a time that does not increase.
    """
    table = read_numeric_table(path, 8, what="TUM trajectory 'timestamp tx ty tz qx qy qz qw'")
    v = table.values
    check_increasing(path, v[:, 0], table.lines, strict=True, what="trajectory timestamps")
    return Trajectory(v[:, 0].copy(), _poses_from_quat(path, table.lines, v[:, 1:4], v[:, 4:8]))


def read_euroc_groundtruth(path: Path) -> Trajectory:
    """Read EuRoC ``state_groundtruth_estimate0/data.csv``: the pose of the body (IMU) frame in the world.

    Columns: t [ns], p_RS_R x y z [m], q_RS w x y z, then velocity and biases (ignored).
    Returns T_w_b (body poses); the EuRoC reader converts them to camera poses.
    """
    what = "EuRoC ground truth 't[ns], px, py, pz, qw, qx, qy, qz, ...'"
    rows = read_rows(path, sep=",", what=what)
    check_columns(path, rows, 8, what, at_least=True)
    ns = np.array([parse_int(path, r, 0, what) for r in rows], dtype=np.int64)
    vals = np.array([[parse_float(path, r, c, what) for c in range(1, 8)] for r in rows], dtype=np.float64)
    vals = vals.reshape(len(rows), 7)
    lines = np.array([r.line for r in rows], dtype=np.int64)
    t_s = ns_to_s(ns)
    check_increasing(path, t_s, lines, strict=True, what="ground-truth timestamps")
    q_xyzw = vals[:, [4, 5, 6, 3]]  # EuRoC writes w first
    return Trajectory(t_s, _poses_from_quat(path, lines, vals[:, 0:3], q_xyzw))


def read_kitti_poses(path: Path, t_s: F64) -> Trajectory:
    """Read KITTI ``poses/NN.txt``: one row-major 3x4 [R | t] per line, T_w_c of camera 0 (world = frame 0).

    t_s: (M,) s from times.txt, M >= number of pose lines (a truncated pose file covers a prefix).
    """
    table = read_numeric_table(path, 12, what="KITTI pose: 12 numbers of a row-major 3x4 matrix")
    n = len(table)
    if n > t_s.shape[0]:
        raise DatasetError(
            f"{path}:{int(table.lines[t_s.shape[0]])}: {n} poses but times.txt has only {t_s.shape[0]} times"
        )
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :] = table.values.reshape(n, 3, 4)
    return Trajectory(t_s[:n].astype(np.float64), T)


def transform_trajectory(traj: Trajectory, T_b_c: F64) -> Trajectory:
    """Right-multiply every pose: T_w_b -> T_w_c = T_w_b @ T_b_c (e.g. body poses to camera poses)."""
    return Trajectory(traj.t_s.copy(), traj.T_w_c @ T_b_c[None, :, :])


def poses_at(traj: Trajectory, t_query: F64, max_gap_s: float) -> list[F64 | None]:
    """Ground-truth pose at each query time, interpolated between the two samples that bracket it.

    Translation is linear and rotation SLERP between samples t0 <= t <= t1, used only when
    t1 - t0 <= ``max_gap_s`` (a wider gap is a tracking dropout: no ground truth there). A query equal
    to a sample time returns that sample. Queries outside [t_first, t_last] get None.
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
        t0, t1 = t[j - 1], t[j]
        if t1 - t0 > max_gap_s:
            continue
        a = (tq - t0) / (t1 - t0)
        T = np.eye(4)
        T[:3, :3] = Slerp([t0, t1], rots[j - 1 : j + 1])([tq]).as_matrix()[0]
        T[:3, 3] = (1.0 - a) * traj.T_w_c[j - 1, :3, 3] + a * traj.T_w_c[j, :3, 3]
        out[k] = T
    return out
