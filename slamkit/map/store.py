"""The default MapStore: the map's entities and graphs in memory, behind one readers-writer lock."""

from __future__ import annotations

from collections.abc import Iterable
from contextlib import AbstractContextManager
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slamkit.errors import ConfigError
from slamkit.map.entities import KeyFrame, MapPoint, mirror_in, mirror_of, set_unmirrored
from slamkit.map.graphs import CovisibilityGraph, SpanningTree, essential_graph_edges
from slamkit.map.lock import ReadWriteLock
from slamkit.map.point_table import SYNCED_ATTRIBUTES, PointTable


class InMemoryMapStore:
    """Keyframes, map points, the covisibility graph, the spanning tree and loop edges of one map.

    Callers take ``read()`` / ``write()`` around access from several threads (the sequential runner needs
    no locking, but taking the lock is cheap). Ids come from the store's own monotonic counters and are
    never reused. ``epoch`` is bumped by large corrections (loop closure) so tracking notices them.

    covisibility_min_shared: ORB-SLAM III-D, an edge needs at least 15 shared points.
    """

    def __init__(self, covisibility_min_shared: int = 15) -> None:
        if covisibility_min_shared < 1:
            raise ConfigError(f"map.covisibility_min_shared must be >= 1, got {covisibility_min_shared}")
        self.covisibility_min_shared = int(covisibility_min_shared)
        self._lock = ReadWriteLock()
        self._keyframes: dict[int, KeyFrame] = {}
        self._points: dict[int, MapPoint] = {}
        self._table = PointTable()  # the points' geometry as arrays by id (tracking's gathers)
        self._next_kf_id = 0
        self._next_point_id = 0
        self._epoch = 0
        self._origin: int | None = None  # cached smallest keyframe id (see origin_keyframe_id)
        self.covisibility = CovisibilityGraph()
        self.spanning_tree = SpanningTree()
        self.loop_edges: set[tuple[int, int]] = set()

    # ---- locking and epoch -----------------------------------------------------------------

    @property
    def epoch(self) -> int:
        return self._epoch

    def bump_epoch(self) -> int:
        self._epoch += 1
        return self._epoch

    def read(self) -> AbstractContextManager[None]:
        return self._lock.read()

    def write(self) -> AbstractContextManager[None]:
        return self._lock.write()

    # ---- ids ----------------------------------------------------------------------------------

    def new_keyframe_id(self) -> int:
        self._next_kf_id += 1
        return self._next_kf_id - 1

    def new_point_id(self) -> int:
        self._next_point_id += 1
        return self._next_point_id - 1

    # ---- entities -----------------------------------------------------------------------------

    def keyframe_ids(self) -> list[int]:
        return sorted(self._keyframes)

    def point_ids(self) -> list[int]:
        return sorted(self._points)

    def n_keyframes(self) -> int:
        return len(self._keyframes)

    def n_points(self) -> int:
        return len(self._points)

    def origin_keyframe_id(self) -> int:
        """The smallest keyframe id in the map (the origin BA holds fixed), without sorting every id."""
        if self._origin is None or self._origin not in self._keyframes:
            if not self._keyframes:
                raise ValueError("the map has no keyframe, so no origin keyframe")
            self._origin = min(self._keyframes)
        return self._origin

    def has_keyframe(self, keyframe_id: int) -> bool:
        return keyframe_id in self._keyframes

    def has_point(self, point_id: int) -> bool:
        return point_id in self._points

    def get_keyframe(self, keyframe_id: int) -> KeyFrame:
        return self._keyframes[keyframe_id]

    def get_point(self, point_id: int) -> MapPoint:
        return self._points[point_id]

    def get_points(self, point_ids: Iterable[int]) -> list[MapPoint]:
        """The points among ``point_ids`` still in the map, in the given order (erased ids are skipped).

        One call instead of has_point/get_point per id: the per-point loops of local mapping use it."""
        points = self._points
        return [points[p] for p in point_ids if p in points]

    def add_keyframe(self, keyframe: KeyFrame) -> None:
        if keyframe.id in self._keyframes:
            raise ValueError(f"keyframe {keyframe.id} is already in the map")
        self._keyframes[keyframe.id] = keyframe
        self.covisibility.add_node(keyframe.id)
        if self._origin is not None and keyframe.id < self._origin:
            self._origin = keyframe.id

    def point_rows(self, point_ids: NDArray[np.int64], attribute: str) -> NDArray[Any]:
        """(K, ...) array of one attribute of K points that are all in the map: "xyz_w" (K, 3) m, "normal_w"
        (K, 3), "d_min_m" / "d_max_m" (K,) m, "descriptor" (K, B) uint8. One indexing of the point table, which
        every change of those attributes reaches (see slamkit/map/point_table.py)."""
        return self._table.rows(np.asarray(point_ids, np.int64), attribute)

    def assign_points(self, points: list[MapPoint], attribute: str, values: NDArray[Any]) -> None:
        """points[i].<attribute> = values[i] for points of this map, with their point-table rows written in one
        indexing (bulk updates: refresh, bundle adjustment, loop correction). values: (K, ...) for K points;
        each point gets its own row of a private copy."""
        if len(points) != len(values):
            raise ValueError(f"assign_points: {len(points)} points but {len(values)} values of {attribute}")
        if not points:
            return
        own = np.array(values, copy=True)
        for point, value in zip(points, own, strict=True):
            if mirror_of(point) is not self._table:
                raise ValueError(f"assign_points: map point {point.id} is not in this map")
            set_unmirrored(point, attribute, value.item() if own.ndim == 1 else value)
        self._table.assign(np.array([p.id for p in points], np.int64), attribute, own)

    def add_point(self, point: MapPoint) -> None:
        if point.id in self._points:
            raise ValueError(f"map point {point.id} is already in the map")
        self._table.put(point.id, {name: getattr(point, name) for name, _, _ in SYNCED_ATTRIBUTES})
        mirror_in(point, self._table)  # from now on its attribute writes reach the table
        self._points[point.id] = point

    def _forget_point(self, point_id: int) -> MapPoint:
        point = self._points.pop(point_id)
        mirror_in(point, None)
        return point

    def remove_point(self, point_id: int) -> None:
        """Erase a point and its observations from every keyframe that saw it."""
        point = self._forget_point(point_id)
        for kf_id, idx in point.observations.items():
            kf = self._keyframes.get(kf_id)
            if kf is not None and kf.point_ids[idx] == point_id:
                kf.point_ids[idx] = -1

    def remove_keyframe(self, keyframe_id: int) -> None:
        """Erase a keyframe: its observations, graph edges and spanning-tree node (children re-parented).

        Points left with no observation are erased too.
        """
        kf = self._keyframes[keyframe_id]
        for idx, pid in enumerate(kf.point_ids):
            if pid < 0:
                continue
            point = self._points.get(int(pid))
            if point is None:
                continue
            point.observations.pop(keyframe_id, None)
            if not point.observations:
                self._forget_point(int(pid))
            elif point.ref_kf_id == keyframe_id:
                point.ref_kf_id = min(point.observations)
            kf.point_ids[idx] = -1
        self.spanning_tree.remove(keyframe_id, self.covisibility)
        self.covisibility.remove(keyframe_id)
        self.loop_edges = {e for e in self.loop_edges if keyframe_id not in e}
        del self._keyframes[keyframe_id]

    # ---- observations and graphs ----------------------------------------------------------------

    def add_observation(self, point_id: int, keyframe_id: int, feature_index: int) -> None:
        """Record that feature ``feature_index`` of a keyframe observes a point (both directions)."""
        self._points[point_id].observations[keyframe_id] = feature_index
        self._keyframes[keyframe_id].point_ids[feature_index] = point_id

    def remove_observation(self, point_id: int, keyframe_id: int) -> None:
        """Forget that a keyframe observes a point; a point left with fewer than two observations is erased
        (ORB-SLAM MapPoint::EraseObservation sets it bad)."""
        point = self._points[point_id]
        idx = point.observations.pop(keyframe_id, None)
        kf = self._keyframes.get(keyframe_id)
        if idx is not None and kf is not None and kf.point_ids[idx] == point_id:
            kf.point_ids[idx] = -1
        if len(point.observations) < 2:
            self.remove_point(point_id)
        elif point.ref_kf_id == keyframe_id:
            point.ref_kf_id = min(point.observations)

    def shared_point_counts(self, keyframe_id: int) -> dict[int, int]:
        """Other keyframe id -> number of map points it shares with ``keyframe_id``."""
        counts: dict[int, int] = {}
        for pid in self._keyframes[keyframe_id].point_ids:
            if pid < 0:
                continue
            point = self._points.get(int(pid))
            if point is None:
                continue
            for other in point.observations:
                if other != keyframe_id:
                    counts[other] = counts.get(other, 0) + 1
        return counts

    def update_connections(self, keyframe_id: int) -> None:
        """Recompute a keyframe's covisibility edges; a keyframe entering the spanning tree gets as parent
        the keyframe it shares most points with (III-D)."""
        shared = self.shared_point_counts(keyframe_id)
        self.covisibility.update_connections(keyframe_id, shared, self.covisibility_min_shared)
        if keyframe_id not in self.spanning_tree:
            neighbors = self.covisibility.neighbors(keyframe_id)
            self.spanning_tree.add(keyframe_id, neighbors[0] if neighbors else None)

    def add_loop_edge(self, a: int, b: int) -> None:
        self.loop_edges.add((min(a, b), max(a, b)))

    def essential_graph(self, theta_min: int) -> list[tuple[int, int]]:
        """Essential-graph edges (III-D) with the given covisibility threshold (ORB-SLAM: 100)."""
        return essential_graph_edges(self.covisibility, self.spanning_tree, self.loop_edges, theta_min)
