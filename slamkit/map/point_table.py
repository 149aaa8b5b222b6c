"""PointTable: the map points' attributes as arrays indexed by point id, kept in step with the points by the store.

Tracking gathers the position, descriptor, viewing direction and scale range of thousands of map points per
frame, and counts which of them were visible and found. Read one object at a time that was ~2 ms of Python per
frame, which beside local mapping's Python runs at half speed under the GIL; gathered from these arrays it is
one numpy indexing per attribute.

The in-memory store writes a point's row whenever it changes one of SYNCED_ATTRIBUTES of the point (every change
goes through the store: entities are read-only, see entities.py), so the table is never stale. The counters
(COUNTERS) live only here. Rows of erased points stay allocated (ids are never reused): ~130 bytes per point id
up to the largest in the map; with an allocator shared by several maps (an Atlas) that counts the ids the other
maps took too.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

#: The MapPoint attributes mirrored in the table: (name, columns or 0 for a scalar, dtype).
SYNCED_ATTRIBUTES: tuple[tuple[str, int, type], ...] = (
    ("xyz_w", 3, np.float64),
    ("normal_w", 3, np.float64),
    ("d_min_m", 0, np.float64),
    ("d_max_m", 0, np.float64),
    ("descriptor", -1, np.uint8),  # width from the first point (32 bytes for ORB)
)

#: Per-point counters kept only in the table (int64): frames that predicted the point visible / that matched it
#: (ORB-SLAM VI-B, both start at 1), the number of keyframes observing it, and ORB-SLAM's MapPoint::Observations()
#: (``n_observations_orbslam``: an observation whose keypoint has a right coordinate, stereo or RGB-D, counts 2).
COUNTERS: tuple[str, ...] = ("n_visible", "n_found", "n_observations", "n_observations_orbslam")

#: Row states: never added, in the map, erased.
ABSENT, PRESENT, ERASED = 0, 1, 2


class PointTable:
    """Arrays by point id: xyz_w (cap, 3) m, normal_w (cap, 3), d_min_m / d_max_m (cap,) m, descriptor (cap, B),
    n_visible / n_found / n_observations / n_observations_orbslam (cap,) int64, state (cap,) int8 (ABSENT, PRESENT, ERASED)."""

    def __init__(self, capacity: int = 4096) -> None:
        self._capacity = max(int(capacity), 1)
        self._descriptor_bytes: int | None = None
        self._arrays: dict[str, NDArray[Any]] = {
            **{name: np.zeros(self._capacity, np.int64) for name in COUNTERS},
            "state": np.zeros(self._capacity, np.int8),
        }

    def _allocate(self, descriptor_bytes: int) -> None:
        self._descriptor_bytes = descriptor_bytes
        for name, width, dtype in SYNCED_ATTRIBUTES:
            w = descriptor_bytes if width < 0 else width
            shape = (self._capacity, w) if w else (self._capacity,)
            self._arrays[name] = np.zeros(shape, dtype)

    def _ensure_row(self, point_id: int) -> None:
        if point_id < self._capacity:
            return
        capacity = self._capacity
        while capacity <= point_id:
            capacity *= 2
        for name, array in self._arrays.items():
            grown = np.zeros((capacity, *array.shape[1:]), array.dtype)
            grown[: self._capacity] = array
            self._arrays[name] = grown
        self._capacity = capacity

    def put(self, point_id: int, values: dict[str, Any]) -> None:
        """Write a new point's row: values maps every synced attribute name to the point's value; the counters
        start at n_visible = n_found = 1, n_observations = n_observations_orbslam = 0."""
        descriptor = np.asarray(values["descriptor"])
        if self._descriptor_bytes is None:
            self._allocate(int(descriptor.shape[-1]))
        elif descriptor.shape != (self._descriptor_bytes,):
            raise ValueError(
                f"map point {point_id}: descriptor of shape {descriptor.shape}, the map holds "
                f"({self._descriptor_bytes},) descriptors"
            )
        self._ensure_row(point_id)
        for name, value in values.items():
            self._arrays[name][point_id] = value
        self._arrays["n_visible"][point_id] = 1
        self._arrays["n_found"][point_id] = 1
        self._arrays["n_observations"][point_id] = 0
        self._arrays["n_observations_orbslam"][point_id] = 0
        self._arrays["state"][point_id] = PRESENT

    def put_many(self, point_ids: NDArray[np.int64], values: dict[str, NDArray[Any]]) -> None:
        """Write the rows of new points ``point_ids`` (K,) at once: values maps every synced attribute name and every
        counter to a (K, ...) array (a saved map's points, MapStore.restore)."""
        ids = np.asarray(point_ids, np.int64)
        if not ids.size:
            return
        descriptors = np.asarray(values["descriptor"])
        if self._descriptor_bytes is None:
            self._allocate(int(descriptors.shape[-1]))
        elif descriptors.shape[1:] != (self._descriptor_bytes,):
            raise ValueError(f"descriptors of shape {descriptors.shape[1:]}, the map holds ({self._descriptor_bytes},)")
        self._ensure_row(int(ids.max()))
        for name, value in values.items():
            self._arrays[name][ids] = value
        self._arrays["state"][ids] = PRESENT

    def is_empty(self) -> bool:
        """True when no point was ever put in the table."""
        return not np.any(self._arrays["state"])

    def erase(self, point_id: int) -> None:
        """Mark a point's row erased (it stays allocated; the id is never used again)."""
        self._arrays["state"][point_id] = ERASED

    def state(self, point_ids: NDArray[np.int64]) -> NDArray[np.int8]:
        """(K,) the row state of any ids (negative or beyond the table: ABSENT)."""
        ids = np.asarray(point_ids, np.int64)
        out = np.zeros(ids.shape, np.int8)
        inside = (ids >= 0) & (ids < self._capacity)
        out[inside] = self._arrays["state"][ids[inside]]
        return out

    def set(self, point_id: int, name: str, value: Any) -> None:
        """One attribute of a point already in the table."""
        self._arrays[name][point_id] = value

    def increment(self, point_id: int, name: str, delta: int) -> None:
        """counter[point_id] += delta for one point already in the table."""
        self._arrays[name][point_id] += delta

    def value(self, point_id: int, name: str) -> Any:
        """Attribute or counter ``name`` of one point already in the table (a numpy scalar, or a row copy)."""
        value = self._arrays[name][point_id]
        return value.copy() if isinstance(value, np.ndarray) else value

    def add(self, point_ids: NDArray[np.int64], name: str, amounts: NDArray[np.int64] | int) -> None:
        """counter[point_ids] += amounts, an id listed twice counted twice (points already in the table)."""
        np.add.at(self._arrays[name], point_ids, amounts)

    def assign(self, point_ids: NDArray[np.int64], name: str, values: NDArray[Any]) -> None:
        """Rows ``point_ids`` (K,) of attribute ``name`` := values (K, ...) (points already in the table)."""
        self._arrays[name][point_ids] = values

    def rows(self, point_ids: NDArray[np.int64], name: str) -> NDArray[Any]:
        """(K, ...) copy of attribute ``name`` of the points ``point_ids`` (K,), which must be in the map."""
        if self._descriptor_bytes is None:
            raise KeyError("the point table is empty")
        return self._arrays[name][point_ids]
