"""Keyframes loop closing is using, which local mapping's keyframe culling must leave in the map (ORB-SLAM's
KeyFrame::SetNotErase / SetErase), held as data by loop closing and read by culling rather than as a flag on the
entity (DESIGN section 4: algorithm-private state lives in the algorithm).

Loop detection runs while local mapping goes on: it pins the current keyframe and its candidates while it works on
them, and an accepted loop keeps the current and the loop keyframe pinned until its correction. Pins are counted,
so two uses of one keyframe need two releases. Thread-safe (its own lock); loop closing pins a keyframe while it
holds the map's read lock and has just seen the keyframe in the map, and culling reads the pins under the map's
write lock, so a keyframe is never culled between the two.
"""

from __future__ import annotations

import threading
from collections import Counter


class KeyFramePins:
    """A counted set of pinned keyframe ids."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._count: Counter[int] = Counter()
        self.total_pinned = 0  # pins taken over the run (for tests and logs)

    def pin(self, *kf_ids: int) -> None:
        with self._lock:
            self._count.update(kf_ids)
            self.total_pinned += len(kf_ids)

    def unpin(self, *kf_ids: int) -> None:
        with self._lock:
            self._count.subtract(kf_ids)
            for k in kf_ids:
                if self._count[k] <= 0:
                    del self._count[k]

    def snapshot(self) -> frozenset[int]:
        """The ids pinned now."""
        with self._lock:
            return frozenset(self._count)

    def __contains__(self, kf_id: object) -> bool:
        with self._lock:
            return kf_id in self._count
