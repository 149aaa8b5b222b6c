"""PLY point cloud of the map points (binary little-endian), for Open3D, CloudCompare, MeshLab and the like.

One vertex per map point of the exported maps: ``x y z`` (double, m, each map's world frame), ``red green blue``
(uchar, the colour of the keyframe images at the point's observations, slamkit/export/colours.py), ``map_id``
(int: which map of the Atlas; maps do not share a world frame until merged) and ``point_id`` (uint: the map
point's id). Format: Paul Bourke's PLY description (the header's ``format binary_little_endian 1.0``, ``element
vertex N``, ``property TYPE NAME`` lines, ``end_header``, then the records packed with no padding).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from .files import atomic_write_bytes
from .snapshot import MapSnapshot

#: The vertex record: (PLY property name, PLY type, numpy little-endian type).
VERTEX_PROPERTIES: tuple[tuple[str, str, str], ...] = (
    ("x", "double", "<f8"),
    ("y", "double", "<f8"),
    ("z", "double", "<f8"),
    ("red", "uchar", "u1"),
    ("green", "uchar", "u1"),
    ("blue", "uchar", "u1"),
    ("map_id", "int", "<i4"),
    ("point_id", "uint", "<u4"),
)


def ply_bytes(snapshots: Sequence[MapSnapshot], colours: Sequence[NDArray[np.uint8]]) -> bytes:
    """The PLY file of the snapshots' points; colours[i]: (P_i, 3) uint8 RGB of snapshots[i]'s points."""
    dtype = np.dtype([(name, np_type) for name, _, np_type in VERTEX_PROPERTIES])
    n = sum(s.n_points for s in snapshots)
    rows = np.zeros(n, dtype)
    start = 0
    for snap, rgb in zip(snapshots, colours, strict=True):
        end = start + snap.n_points
        part = rows[start:end]
        part["x"], part["y"], part["z"] = snap.xyz_w[:, 0], snap.xyz_w[:, 1], snap.xyz_w[:, 2]
        part["red"], part["green"], part["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
        part["map_id"] = snap.map_id
        part["point_id"] = snap.point_ids
        start = end
    maps = ", ".join(f"map {s.map_id}: {s.n_points} points" for s in snapshots) or "no map"
    header = [
        "ply",
        "format binary_little_endian 1.0",
        f"comment slamkit map export ({maps}); x y z in metres, each map's world frame",
        f"element vertex {n}",
        *(f"property {ply_type} {name}" for name, ply_type, _ in VERTEX_PROPERTIES),
        "end_header",
    ]
    return ("\n".join(header) + "\n").encode("ascii") + rows.tobytes()


def write_ply(path: Path, snapshots: Sequence[MapSnapshot], colours: Sequence[NDArray[np.uint8]]) -> Path:
    """Write the PLY file at ``path`` (atomically: a failed export leaves no partial file). Returns path."""
    atomic_write_bytes(path, ply_bytes(snapshots, colours))
    return path
