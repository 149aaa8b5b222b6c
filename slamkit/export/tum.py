"""The keyframe trajectory of a map as a TUM file (``t x y z qx qy qz qw``, T_w_c), written exactly as the run's
own keyframes.tum (slamkit/io/trajectory_io.py, full float64 precision; keyframes in time order)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slamkit.io.trajectory_io import write_trajectory
from slamkit.sensors import Trajectory

from .snapshot import MapSnapshot


def keyframe_trajectory(snap: MapSnapshot) -> Trajectory:
    """The map's keyframes as a Trajectory, T_w_c in time order (ties: keyframe id)."""
    order = sorted(snap.keyframes, key=lambda kf: (kf.timestamp_s, kf.id))
    t_s = np.array([kf.timestamp_s for kf in order], np.float64)
    T_w_c = np.stack([kf.T_w_c for kf in order]) if order else np.zeros((0, 4, 4))
    return Trajectory(t_s, T_w_c)


def write_tum(path: Path, snap: MapSnapshot) -> Path:
    """Write the map's keyframe trajectory at ``path``. Returns path."""
    path.parent.mkdir(parents=True, exist_ok=True)
    write_trajectory(path, keyframe_trajectory(snap), "tum")
    return path
