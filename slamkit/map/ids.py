"""Id allocation for map entities: monotonic counters that several maps can share.

ORB-SLAM3's Atlas holds several maps whose keyframe and map point ids are unique across all of them. A MapStore
takes its ids from an ``IdAllocator``; stores built with the same allocator never hand out the same id, and an
id is never reused (DESIGN section 5).
"""

from __future__ import annotations

import threading


class IdAllocator:
    """Thread-safe monotonic counters of keyframe ids and map point ids, starting at 0 (or where a saved map's
    allocator stopped: ``next_keyframe`` / ``next_point``, the next ids it hands out; slamkit/map/mapfile.py)."""

    def __init__(self, next_keyframe: int = 0, next_point: int = 0) -> None:
        if next_keyframe < 0 or next_point < 0:
            raise ValueError(f"IdAllocator: next ids must be >= 0, got {next_keyframe}, {next_point}")
        self._lock = threading.Lock()
        self._next_keyframe = int(next_keyframe)
        self._next_point = int(next_point)

    def next_ids(self) -> tuple[int, int]:
        """(next keyframe id, next map point id) it will hand out: the state a saved map records."""
        with self._lock:
            return self._next_keyframe, self._next_point

    def new_keyframe_id(self) -> int:
        with self._lock:
            self._next_keyframe += 1
            return self._next_keyframe - 1

    def new_point_id(self) -> int:
        with self._lock:
            self._next_point += 1
            return self._next_point - 1

    def issued_keyframe(self, keyframe_id: int) -> bool:
        """Whether ``keyframe_id`` has been handed out by this allocator."""
        return 0 <= keyframe_id < self._next_keyframe

    def issued_point(self, point_id: int) -> bool:
        """Whether ``point_id`` has been handed out by this allocator."""
        return 0 <= point_id < self._next_point
