"""PointTable: the map points' geometric attributes as arrays indexed by point id, kept in step with the points.

Tracking gathers the position, descriptor, viewing direction and scale range of thousands of map points per
frame. Read one object at a time that was ~2 ms of Python per frame, which beside local mapping's Python runs
at half speed under the GIL; gathered from these arrays it is one numpy indexing per attribute.

A MapPoint in a store writes each change of one of SYNCED_ATTRIBUTES through to its row here (the attributes
are properties, see entities.py), so the table is never stale: whoever may assign a point's attribute may rely on
the table reading it back. Changing such an array *in place* (``point.xyz_w[0] = ...``) bypasses the write-through;
assign a new array instead (tests/unit/map/test_point_table.py checks the table against the objects after
whole runs). Rows of erased points stay allocated (ids are never reused): 100 bytes per point ever made.
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


class PointTable:
    """Arrays by point id: xyz_w (cap, 3) m, normal_w (cap, 3), d_min_m / d_max_m (cap,) m, descriptor (cap, B)."""

    def __init__(self, capacity: int = 4096) -> None:
        self._capacity = max(int(capacity), 1)
        self._descriptor_bytes: int | None = None
        self._arrays: dict[str, NDArray[Any]] = {}

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
        """Write a point's row: values maps every synced attribute name to the point's value."""
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

    def set(self, point_id: int, name: str, value: Any) -> None:
        """One attribute of a point already in the table."""
        self._arrays[name][point_id] = value

    def assign(self, point_ids: NDArray[np.int64], name: str, values: NDArray[Any]) -> None:
        """Rows ``point_ids`` (K,) of attribute ``name`` := values (K, ...) (points already in the table)."""
        self._arrays[name][point_ids] = values

    def rows(self, point_ids: NDArray[np.int64], name: str) -> NDArray[Any]:
        """(K, ...) copy of attribute ``name`` of the points ``point_ids`` (K,), which must be in the map."""
        if not self._arrays:
            raise KeyError("the point table is empty")
        return self._arrays[name][point_ids]
