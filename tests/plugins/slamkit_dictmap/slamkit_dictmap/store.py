"""DictMapStore: the MapStore protocol (slamkit.map.protocol) on plain dicts, as small as it can be.

No point table: ``point_rows`` gathers from the point objects one by one, the counters are a dict. One re-entrant
mutex serves as both the read and the write lock (readers exclude each other too: correct, less concurrent). It
reuses slamkit's entities (slamkit.map.entities: KeyFrame, MapPoint and the helpers a store changes them with),
the graph bookkeeping (slamkit.map.graphs) and the id allocator (slamkit.map.ids), and nothing of slamkit's own
store.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from types import MappingProxyType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slamkit.interfaces import BowDescription
from slamkit.map.entities import KeyFrame, MapPoint, frozen_copy, frozen_view, replace_fields
from slamkit.map.graphs import CovisibilityGraph, CovisibilityView, SpanningTree, SpanningTreeView
from slamkit.map.ids import IdAllocator
from slamkit.map.mapfile_contents import MapContents, check_contents

I64 = NDArray[np.int64]

_GEOMETRY = {
    "xyz_w": (3, np.float64),
    "normal_w": (3, np.float64),
    "d_min_m": (0, np.float64),
    "d_max_m": (0, np.float64),
}


class DictMapStore:
    """A map in dicts: keyframe id -> KeyFrame, point id -> MapPoint (+ its observations and counters)."""

    def __init__(self, covisibility_min_shared: int = 15, ids: IdAllocator | None = None) -> None:
        if covisibility_min_shared < 1:
            raise ValueError(f"map.covisibility_min_shared must be >= 1, got {covisibility_min_shared}")
        self.min_shared = int(covisibility_min_shared)
        self._ids = ids if ids is not None else IdAllocator()
        self._mutex = threading.RLock()
        self._counter_mutex = threading.Lock()
        self._kfs: dict[int, KeyFrame] = {}
        self._matches: dict[int, I64] = {}  # keyframe id -> the writable array behind its point_ids
        self._pts: dict[int, MapPoint] = {}
        self._obs: dict[int, dict[int, int]] = {}  # point id -> the dict behind its observations
        self._counts: dict[int, list[int]] = {}  # point id -> [n_visible, n_found]
        self._used_kf_ids: set[int] = set()
        self._used_point_ids: set[int] = set()
        self._graph = CovisibilityGraph()
        self._tree = SpanningTree()
        self._first: int | None = None  # the first keyframe added: the spanning tree's root
        self._loops: set[tuple[int, int]] = set()
        self._epoch = 0

    # ---- locking, epoch, ids ----------------------------------------------------------------------------

    @property
    def epoch(self) -> int:
        return self._epoch

    def bump_epoch(self) -> int:
        self._epoch += 1
        return self._epoch

    @contextmanager
    def _locked(self) -> Iterator[None]:
        with self._mutex:
            yield

    def read(self) -> Any:
        return self._locked()

    def write(self) -> Any:
        return self._locked()

    @property
    def ids(self) -> IdAllocator:
        return self._ids

    def new_keyframe_id(self) -> int:
        return self._ids.new_keyframe_id()

    def new_point_id(self) -> int:
        return self._ids.new_point_id()

    # ---- reads ----------------------------------------------------------------------------------------------

    def keyframe_ids(self) -> list[int]:
        return sorted(self._kfs)

    def point_ids(self) -> list[int]:
        return sorted(self._pts)

    def n_keyframes(self) -> int:
        return len(self._kfs)

    def n_points(self) -> int:
        return len(self._pts)

    def origin_keyframe_id(self) -> int:
        if not self._kfs:
            raise ValueError("the map has no keyframe")
        return min(self._kfs)

    def has_keyframe(self, keyframe_id: int) -> bool:
        return keyframe_id in self._kfs

    def has_point(self, point_id: int) -> bool:
        return point_id in self._pts

    def has_points(self, point_ids: I64) -> NDArray[np.bool_]:
        ids = np.asarray(point_ids).tolist()
        return np.fromiter((p in self._pts for p in ids), bool, len(ids))

    def get_keyframe(self, keyframe_id: int) -> KeyFrame:
        return self._kfs[keyframe_id]

    def get_point(self, point_id: int) -> MapPoint:
        return self._pts[point_id]

    def get_points(self, point_ids: Iterable[int]) -> list[MapPoint]:
        return [self._pts[p] for p in point_ids if p in self._pts]

    def point_rows(self, point_ids: I64, attribute: str) -> NDArray[Any]:
        ids = np.asarray(point_ids).tolist()
        if attribute in ("n_visible", "n_found"):
            col = 0 if attribute == "n_visible" else 1
            return np.array([self._counts[p][col] for p in ids], np.int64)
        if attribute == "n_observations":
            return np.array([len(self._obs[p]) for p in ids], np.int64)
        if attribute == "n_observations_orbslam":  # a keypoint with a right coordinate counts 2 (ORB-SLAM)
            return np.array(
                [
                    sum(2 if np.isfinite(self._kfs[k].features.u_right_px[i]) else 1 for k, i in self._obs[p].items())
                    for p in ids
                ],
                np.int64,
            )
        if attribute == "descriptor":
            width = next((len(p.descriptor) for p in self._pts.values()), 32)
            return np.array([self._pts[p].descriptor for p in ids], np.uint8).reshape(len(ids), width)
        if attribute not in _GEOMETRY:
            raise KeyError(f"no point attribute {attribute!r}")
        cols, dtype = _GEOMETRY[attribute]
        out = np.array([getattr(self._pts[p], attribute) for p in ids], dtype)
        return out.reshape((len(ids), cols) if cols else (len(ids),))

    @property
    def covisibility(self) -> CovisibilityView:
        return CovisibilityView(self._graph)

    @property
    def spanning_tree(self) -> SpanningTreeView:
        return SpanningTreeView(self._tree)

    def loop_edges(self) -> list[tuple[int, int]]:
        return sorted(self._loops)

    # ---- mutations ----------------------------------------------------------------------------------------

    def add_keyframe(self, keyframe: KeyFrame) -> None:
        k = keyframe.id
        if k in self._used_kf_ids or not self._ids.issued_keyframe(k):
            raise ValueError(f"keyframe {k}: id already used or not issued by this map's allocator")
        self._used_kf_ids.add(k)
        if not self._kfs:  # the (possibly reset) map's first keyframe: the spanning tree's root
            self._first = k
        matches = np.array(keyframe.point_ids, np.int64)
        replace_fields(keyframe, point_ids=frozen_view(matches))
        self._kfs[k] = keyframe
        self._matches[k] = matches
        self._graph.add_node(k)
        for idx, pid in enumerate(matches.tolist()):
            if pid < 0:
                continue
            if pid not in self._obs or k in self._obs[pid]:
                matches[idx] = -1
            else:
                self.add_observation(pid, k, idx)

    def add_point(self, point: MapPoint) -> None:
        p = point.id
        if p in self._used_point_ids or not self._ids.issued_point(p):
            raise ValueError(f"map point {p}: id already used or not issued by this map's allocator")
        if point.observations:
            raise ValueError(f"map point {p} comes with observations")
        if self._pts:
            width = len(next(iter(self._pts.values())).descriptor)
            if point.descriptor.shape != (width,):
                raise ValueError(
                    f"map point {p}: descriptor of shape {point.descriptor.shape}, the map holds ({width},)"
                )
        self._used_point_ids.add(p)
        obs: dict[int, int] = {}
        replace_fields(point, observations=MappingProxyType(obs))
        self._pts[p] = point
        self._obs[p] = obs
        self._counts[p] = [1, 1]

    def remove_point(self, point_id: int) -> None:
        del self._pts[point_id]
        del self._counts[point_id]
        for k, idx in self._obs.pop(point_id).items():
            if k in self._matches and self._matches[k][idx] == point_id:
                self._matches[k][idx] = -1

    def remove_keyframe(self, keyframe_id: int) -> None:
        matches = self._matches.pop(keyframe_id)
        for idx, pid in enumerate(matches.tolist()):
            if pid < 0 or pid not in self._obs:
                continue
            obs = self._obs[pid]
            obs.pop(keyframe_id, None)
            if not obs:
                del self._pts[pid], self._counts[pid], self._obs[pid]
            elif self._pts[pid].ref_kf_id == keyframe_id:
                replace_fields(self._pts[pid], ref_kf_id=min(obs))
            matches[idx] = -1
        self._tree.remove(keyframe_id, self._graph)
        self._graph.remove(keyframe_id)
        self._loops = {e for e in self._loops if keyframe_id not in e}
        del self._kfs[keyframe_id]

    def add_observation(self, point_id: int, keyframe_id: int, feature_index: int) -> None:
        self._obs[point_id][keyframe_id] = feature_index
        self._matches[keyframe_id][feature_index] = point_id

    def remove_observation(self, point_id: int, keyframe_id: int) -> None:
        obs = self._obs[point_id]
        idx = obs.pop(keyframe_id, None)
        matches = self._matches.get(keyframe_id)
        if idx is not None and matches is not None and matches[idx] == point_id:
            matches[idx] = -1
        if len(obs) < 2:
            self.remove_point(point_id)
        elif self._pts[point_id].ref_kf_id == keyframe_id:
            replace_fields(self._pts[point_id], ref_kf_id=min(obs))

    def replace_point(self, old_id: int, new_id: int) -> None:
        if old_id == new_id:
            raise ValueError("a point cannot replace itself")
        for k, idx in sorted(self._obs[old_id].items()):
            self._matches[k][idx] = -1
            if k not in self._obs[new_id]:
                self.add_observation(new_id, k, idx)
        with self._counter_mutex:
            self._counts[new_id] = [a + b for a, b in zip(self._counts[new_id], self._counts[old_id], strict=True)]
        self._obs[old_id].clear()
        self.remove_point(old_id)

    def set_keyframe_pose(self, keyframe_id: int, T_c_w: NDArray[np.float64]) -> None:
        replace_fields(self._kfs[keyframe_id], T_c_w=frozen_copy(T_c_w, np.float64))

    def set_keyframe_poses(self, keyframe_ids: Iterable[int], T_c_w: NDArray[np.float64]) -> None:
        for k, T in zip(list(keyframe_ids), T_c_w, strict=True):
            self.set_keyframe_pose(k, T)

    def set_keyframe_bow(self, keyframe_id: int, bow: BowDescription) -> None:
        replace_fields(self._kfs[keyframe_id], bow=bow)

    def assign_points(self, point_ids: I64, attribute: str, values: NDArray[Any]) -> None:
        if attribute not in _GEOMETRY and attribute != "descriptor":
            raise KeyError(f"{attribute!r} is not an assignable point attribute")
        ids = np.asarray(point_ids).tolist()
        if len(ids) != len(values):
            raise ValueError(f"{len(ids)} points but {len(values)} values")
        for p, value in zip(ids, values, strict=True):
            if p not in self._pts:
                raise ValueError(f"map point {p} is not in this map")
            if attribute in ("d_min_m", "d_max_m"):
                replace_fields(self._pts[p], **{attribute: float(value)})
            else:
                replace_fields(self._pts[p], **{attribute: frozen_copy(value, np.asarray(value).dtype)})

    def increase_visible(self, point_ids: I64, n: int = 1) -> None:
        with self._counter_mutex:
            for p in np.asarray(point_ids).tolist():
                self._counts[p][0] += n

    def increase_found(self, point_ids: I64, n: int = 1) -> None:
        with self._counter_mutex:
            for p in np.asarray(point_ids).tolist():
                self._counts[p][1] += n

    def update_connections(self, keyframe_id: int) -> None:
        shared: dict[int, int] = {}
        for pid in self._matches[keyframe_id].tolist():
            for other in self._obs.get(pid, {}) if pid >= 0 else ():
                if other != keyframe_id:
                    shared[other] = shared.get(other, 0) + 1
        self._graph.update_connections(keyframe_id, shared, self.min_shared)
        if keyframe_id not in self._tree:
            best = self._graph.neighbors(keyframe_id)
            self._tree.add(keyframe_id, best[0] if best and keyframe_id != self._first else None)

    def add_loop_edge(self, a: int, b: int) -> None:
        self._loops.add((min(a, b), max(a, b)))

    def restore(self, contents: MapContents) -> None:
        """Fill the empty store with a saved map (MapStore.restore): entities rebuilt, then the saved graphs."""
        if self._used_kf_ids or self._used_point_ids:
            raise ValueError("restore: the map is not empty")
        check_contents(contents, self._ids)
        self._put(contents, None)
        self._loops = {(min(a, b), max(a, b)) for a, b in contents.loop_edges}
        self._first = contents.first_keyframe_id
        self._epoch = int(contents.epoch)

    def add_contents(self, contents: MapContents, roots_parent: int | None = None, checked: bool = False) -> None:
        """Another map's entities and graphs added (MapStore.add_contents)."""
        if not checked:
            check_contents(contents, self._ids)
        if any(kf.id in self._used_kf_ids for kf in contents.keyframes) or any(
            p.id in self._used_point_ids for p in contents.points
        ):
            raise ValueError("add_contents: ids already used in this map")
        if roots_parent is not None and roots_parent not in self._kfs:
            raise ValueError(f"add_contents: {roots_parent} is not a keyframe of this map")
        self._put(contents, roots_parent)
        self._loops |= {(min(a, b), max(a, b)) for a, b in contents.loop_edges}

    def _put(self, contents: MapContents, roots_parent: int | None) -> None:
        for kf in contents.keyframes:
            matches = np.array(kf.point_ids, np.int64)
            entity = KeyFrame(kf.id, kf.frame_index, kf.timestamp_s, kf.T_c_w, kf.camera, kf.features, matches, kf.bow)
            replace_fields(entity, point_ids=frozen_view(matches))
            self._used_kf_ids.add(kf.id)
            self._kfs[kf.id] = entity
            self._matches[kf.id] = matches
            self._graph.add_node(kf.id)
        for p, n_visible, n_found in zip(contents.points, contents.n_visible, contents.n_found, strict=True):
            obs = dict(p.observations)
            entity = MapPoint(p.id, p.xyz_w, p.descriptor, p.ref_kf_id, p.first_kf_id, p.normal_w, p.d_min_m, p.d_max_m)
            replace_fields(entity, observations=MappingProxyType(obs))
            self._used_point_ids.add(p.id)
            self._pts[p.id] = entity
            self._obs[p.id] = obs
            self._counts[p.id] = [int(n_visible), int(n_found)]
        for a, b, w in contents.covisibility.tolist():
            self._graph.set_edge(a, b, w)
        for k, parent in contents.tree.items():
            self._tree.add(k, roots_parent if parent is None else parent)
