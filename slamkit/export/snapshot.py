"""What an exporter reads of a map: a copy of its keyframes and points taken under the map's read lock.

Every exporter (PLY, COLMAP, TUM) works on :class:`MapSnapshot` objects, never on a live store: the read lock is
held only while the snapshot is copied (so a run may go on meanwhile), and the files written from one snapshot are
consistent with each other. Works with any MapStore (through the protocol) and with every map of an Atlas.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slamkit.errors import ExportError
from slamkit.interfaces import Camera, MapStore
from slamkit.map.atlas import Atlas

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass(frozen=True)
class KeyFrameRecord:
    """One keyframe as exported.

    id: the keyframe id (unique across the Atlas). frame_index: the dataset frame it was made from (0-based
    position in the run's sequence). timestamp_s: s. T_c_w: (4, 4) float64 world -> camera. camera: its camera
    model. uv_px: (N, 2) float32 raw-image pixels of its N features (OpenCV convention: the centre of the top-left
    pixel is (0, 0)). point_ids: (N,) int64, the map point each feature observes, -1 for none.
    """

    id: int
    frame_index: int
    timestamp_s: float
    T_c_w: F64
    camera: Camera
    uv_px: NDArray[np.float32]
    point_ids: I64

    @property
    def T_w_c(self) -> F64:
        """(4, 4) camera -> world."""
        R, t = self.T_c_w[:3, :3], self.T_c_w[:3, 3]
        out = np.eye(4)
        out[:3, :3] = R.T
        out[:3, 3] = -R.T @ t
        return out


@dataclass(frozen=True)
class MapSnapshot:
    """One map of the Atlas, copied.

    map_id: the map's id in the Atlas. keyframes: sorted by id. point_ids: (P,) int64 sorted. xyz_w: (P, 3) float64
    m, world frame. tracks: per point, its observations as (keyframe id, feature index) pairs sorted by keyframe id.
    """

    map_id: int
    keyframes: tuple[KeyFrameRecord, ...]
    point_ids: I64
    xyz_w: F64
    tracks: tuple[tuple[tuple[int, int], ...], ...]

    @property
    def n_points(self) -> int:
        return int(self.point_ids.shape[0])


def snapshot_map(store: MapStore, map_id: int = 0) -> MapSnapshot:
    """Copy ``store`` under its read lock (see the module docstring)."""
    with store.read():
        keyframes = []
        for kf_id in store.keyframe_ids():
            kf = store.get_keyframe(kf_id)
            keyframes.append(
                KeyFrameRecord(
                    id=int(kf.id),
                    frame_index=int(kf.frame_index),
                    timestamp_s=float(kf.timestamp_s),
                    T_c_w=np.array(kf.T_c_w, dtype=np.float64),
                    camera=kf.camera,
                    uv_px=np.array(kf.features.uv_px, dtype=np.float32).reshape(-1, 2),
                    point_ids=np.array(kf.point_ids, dtype=np.int64),
                )
            )
        point_ids = np.array(store.point_ids(), dtype=np.int64)
        xyz_w = store.point_rows(point_ids, "xyz_w") if point_ids.size else np.zeros((0, 3))
        tracks = tuple(
            tuple(sorted((int(k), int(f)) for k, f in point.observations.items()))
            for point in store.get_points(point_ids.tolist())
        )
    return MapSnapshot(int(map_id), tuple(keyframes), point_ids, np.asarray(xyz_w, np.float64).reshape(-1, 3), tracks)


def main_map_id(atlas: Atlas) -> int:
    """The map with the most keyframes (ties: the lowest id): the map whose keyframes a run writes to keyframes.tum
    (ORB-SLAM3 SaveKeyFrameTrajectory, slamkit/eval/outputs.py)."""
    return max(atlas.items(), key=lambda item: (item[1].n_keyframes(), -item[0]))[0]


def select_maps(source: Atlas | MapStore, maps: str | int | Sequence[int] = "all") -> tuple[Atlas, list[int]]:
    """(the Atlas, the ids of the maps ``maps`` names): "all" (every map with a keyframe, ascending ids), "main" (the
    map with the most keyframes, as keyframes.tum), a map id or a list of map ids. A MapStore is an Atlas of one map
    (id 0). ExportError for a map id the Atlas does not have."""
    atlas = source if isinstance(source, Atlas) else Atlas.of(source)
    if maps == "all":
        ids = [map_id for map_id, store in atlas.items() if store.n_keyframes() > 0]
    elif maps == "main":
        ids = [main_map_id(atlas)]
    elif isinstance(maps, str):
        raise ExportError(f"maps = {maps!r}: expected 'all', 'main', a map id or a list of map ids")
    else:
        ids = [int(maps)] if isinstance(maps, int | np.integer) else [int(m) for m in maps]
    known = atlas.map_ids()
    missing = [m for m in ids if m not in known]
    if missing:
        raise ExportError(f"map {missing[0]} is not in the Atlas (maps: {', '.join(map(str, known))})")
    return atlas, ids


def snapshot_atlas(source: Atlas | MapStore, maps: str | int | Sequence[int] = "all") -> list[MapSnapshot]:
    """Snapshots of the maps ``maps`` names (see :func:`select_maps`), each under its read lock."""
    atlas, ids = select_maps(source, maps)
    return [snapshot_map(atlas.get(m), m) for m in ids]
