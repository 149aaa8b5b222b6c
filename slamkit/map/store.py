"""The default MapStore (``map=memory``): the map's entities and graphs in memory, behind one readers-writer lock."""

from __future__ import annotations

import threading
from collections import Counter
from collections.abc import Iterable, Sequence
from contextlib import AbstractContextManager
from itertools import chain
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from slamkit.errors import ConfigError
from slamkit.interfaces import BowDescription
from slamkit.map.entities import KeyFrame, MapPoint, frozen_copy, frozen_view, observation_weight, replace_fields
from slamkit.map.graphs import (
    CovisibilityGraph,
    CovisibilityView,
    SpanningTree,
    SpanningTreeView,
)
from slamkit.map.ids import IdAllocator
from slamkit.map.lock import ReadWriteLock
from slamkit.map.mapfile_contents import MapContents, check_contents
from slamkit.map.point_table import COUNTERS, PRESENT, SYNCED_ATTRIBUTES, PointTable
from slamkit.map.protocol import MapStore

I64 = NDArray[np.int64]

_ASSIGNABLE = frozenset(name for name, _, _ in SYNCED_ATTRIBUTES)
_READABLE = _ASSIGNABLE | frozenset(COUNTERS)


class InMemoryMapStore:
    """Keyframes, map points, the covisibility graph, the spanning tree and loop edges of one map
    (implements slamkit.map.protocol.MapStore; see there for what each method promises).

    The entities it hands out are read-only: it keeps the writable arrays behind them (each keyframe's point_ids,
    each point's observation dict) and changes the frozen dataclasses with entities.replace_fields. The points'
    attributes are mirrored, by every mutation, in a PointTable indexed by id, from which ``point_rows`` gathers;
    the visible/found counters live only there.

    covisibility_min_shared: ORB-SLAM III-D, an edge needs at least 15 shared points. ids: the allocator of
    keyframe and point ids (shared by the maps of an Atlas); default a private one.
    """

    def __init__(self, covisibility_min_shared: int = 15, ids: IdAllocator | None = None) -> None:
        if covisibility_min_shared < 1:
            raise ConfigError(f"map.covisibility_min_shared must be >= 1, got {covisibility_min_shared}")
        self.covisibility_min_shared = int(covisibility_min_shared)
        self._ids = ids if ids is not None else IdAllocator()
        self._lock = ReadWriteLock()
        self._counter_lock = threading.Lock()  # increase_visible/found run under the read lock
        self._keyframes: dict[int, KeyFrame] = {}
        self._kf_point_ids: dict[int, I64] = {}  # the writable arrays behind the keyframes' point_ids
        self._erased_keyframes: set[int] = set()
        self._points: dict[int, MapPoint] = {}
        self._observations: dict[int, dict[int, int]] = {}  # behind the points' read-only observations
        self._table = PointTable()  # the points' attributes as arrays by id (tracking's gathers)
        self._epoch = 0
        self._origin: int | None = None  # cached smallest keyframe id (see origin_keyframe_id)
        self._covisibility = CovisibilityGraph()
        self._tree = SpanningTree()
        self._first_keyframe: int | None = None  # the map's initial keyframe: the root of its spanning tree
        self._loop_edges: set[tuple[int, int]] = set()
        self._covisibility_view = CovisibilityView(self._covisibility)
        self._tree_view = SpanningTreeView(self._tree)

    # ---- locking, epoch, ids -------------------------------------------------------------------------

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

    @property
    def write_count(self) -> int:
        """How many times the map's write lock was released so far (not in the MapStore protocol: loop correction
        computes under the read lock and writes under the write lock, and checks with it that nobody wrote in
        between; slamkit.pipeline.loop_correction.read_then_write)."""
        return self._lock.writes

    @property
    def ids(self) -> IdAllocator:
        return self._ids

    def new_keyframe_id(self) -> int:
        return self._ids.new_keyframe_id()

    def new_point_id(self) -> int:
        return self._ids.new_point_id()

    # ---- entities (read) ---------------------------------------------------------------------------------

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

    def has_points(self, point_ids: I64) -> NDArray[np.bool_]:
        return np.asarray(self._table.state(np.asarray(point_ids, np.int64)) == PRESENT)

    def get_keyframe(self, keyframe_id: int) -> KeyFrame:
        return self._keyframes[keyframe_id]

    def get_point(self, point_id: int) -> MapPoint:
        return self._points[point_id]

    def get_points(self, point_ids: Iterable[int]) -> list[MapPoint]:
        points = self._points
        return [points[p] for p in point_ids if p in points]

    def flat_observations(self, point_ids: I64) -> tuple[I64, I64, I64]:
        """``slamkit.pipeline.map_points.flat_observations(self.get_points(point_ids))`` (the points must be in the
        map) read from the store's own dictionaries, without the points' read-only views: (counts (P,), kf (E,),
        feat (E,)), point q's observations at rows sum(counts[:q]):sum(counts[:q + 1]) in its observation order."""
        observations = self._observations
        obs = [observations[p] for p in np.asarray(point_ids, np.int64).tolist()]
        counts = np.fromiter(map(len, obs), np.int64, count=len(obs))
        E = int(counts.sum())
        kf = np.fromiter(chain.from_iterable(obs), np.int64, count=E)
        feat = np.fromiter(chain.from_iterable(map(dict.values, obs)), np.int64, count=E)
        return counts, kf, feat

    def point_rows(self, point_ids: I64, attribute: str) -> NDArray[Any]:
        if attribute not in _READABLE:
            raise KeyError(f"point_rows: no point attribute {attribute!r} (one of {', '.join(sorted(_READABLE))})")
        return self._table.rows(np.asarray(point_ids, np.int64), attribute)

    # ---- graphs (read) -----------------------------------------------------------------------------------

    @property
    def covisibility(self) -> CovisibilityView:
        return self._covisibility_view

    @property
    def spanning_tree(self) -> SpanningTreeView:
        return self._tree_view

    def loop_edges(self) -> list[tuple[int, int]]:
        return sorted(self._loop_edges)

    def shared_point_counts(self, keyframe_id: int) -> dict[int, int]:
        """Other keyframe id -> number of map points it shares with ``keyframe_id``."""
        own = self._kf_point_ids[keyframe_id]
        get = self._observations.get
        # every observer of every point, counted by Counter's C loop over the chained observation dicts: the same
        # counts in the same first-seen order as a loop over the points and their observers
        counts = Counter(chain.from_iterable(filter(None, map(get, own[own >= 0].tolist()))))
        counts.pop(keyframe_id, None)
        return dict(counts)

    # ---- mutations: entities ---------------------------------------------------------------------------

    def add_keyframe(self, keyframe: KeyFrame) -> None:
        kf_id = keyframe.id
        if kf_id in self._keyframes or kf_id in self._erased_keyframes:
            raise ValueError(f"keyframe {kf_id} is already in the map or was erased from it (ids are not reused)")
        if not self._ids.issued_keyframe(kf_id):
            raise ValueError(f"keyframe {kf_id}: its id was not issued by this map's id allocator")
        if not self._keyframes:
            # the first keyframe of the (possibly reset) map: the spanning tree's root (ORB-SLAM3 Map::AddKeyFrame sets
            # mnInitKFid when the map is empty; a map emptied by Atlas.reset_active starts again from its next one)
            self._first_keyframe = kf_id
        own = np.array(keyframe.point_ids, np.int64)
        replace_fields(keyframe, point_ids=frozen_view(own))
        self._kf_point_ids[kf_id] = own
        self._keyframes[kf_id] = keyframe
        self._covisibility.add_node(kf_id)
        if self._origin is not None and kf_id < self._origin:
            self._origin = kf_id
        # each feature naming a point in the map observes it, the first of two features naming the same point only
        # (the others, and those naming a point gone, become -1): the per-feature rule, written at once
        idx = np.flatnonzero(own >= 0)
        pids = own[idx]
        keep = self._table.state(pids) == PRESENT
        first = np.zeros(idx.size, bool)
        first[np.unique(pids, return_index=True)[1]] = True
        keep &= first
        own[idx[~keep]] = -1
        self.add_observations(pids[keep], kf_id, idx[keep])

    def add_point(self, point: MapPoint) -> None:
        pid = point.id
        if pid in self._points or self._table.state(np.array([pid]))[0] != 0:
            raise ValueError(f"map point {pid} is already in the map or was erased from it (ids are not reused)")
        if not self._ids.issued_point(pid):
            raise ValueError(f"map point {pid}: its id was not issued by this map's id allocator")
        if point.observations:
            raise ValueError(f"map point {pid} comes with observations: add them with add_observation")
        self._table.put(pid, {name: getattr(point, name) for name, _, _ in SYNCED_ATTRIBUTES})
        obs: dict[int, int] = {}
        replace_fields(point, observations=MappingProxyType(obs))
        self._observations[pid] = obs
        self._points[pid] = point

    def add_points(self, points: Sequence[MapPoint]) -> None:
        points = list(points)
        if not points:
            return
        ids = np.array([p.id for p in points], np.int64)
        # add_point's checks for every point before any is added
        if np.unique(ids).size != ids.size:
            raise ValueError("add_points: two of the points share an id")
        for point in points:
            pid = point.id
            if pid in self._points:
                raise ValueError(f"map point {pid} is already in the map or was erased from it (ids are not reused)")
            if not self._ids.issued_point(pid):
                raise ValueError(f"map point {pid}: its id was not issued by this map's id allocator")
            if point.observations:
                raise ValueError(f"map point {pid} comes with observations: add them with add_observation")
        erased = np.flatnonzero(self._table.state(ids) != 0)
        if erased.size:
            pid = int(ids[erased[0]])
            raise ValueError(f"map point {pid} is already in the map or was erased from it (ids are not reused)")
        rows: dict[str, NDArray[Any]] = {
            name: np.array([getattr(p, name) for p in points]) for name, _, _ in SYNCED_ATTRIBUTES
        }
        rows["n_visible"] = np.ones(ids.size, np.int64)
        rows["n_found"] = np.ones(ids.size, np.int64)
        rows["n_observations"] = np.zeros(ids.size, np.int64)
        rows["n_observations_orbslam"] = np.zeros(ids.size, np.int64)
        self._table.put_many(ids, rows)  # raises for a descriptor width unlike the map's, before the dicts change
        for point in points:
            obs: dict[int, int] = {}
            replace_fields(point, observations=MappingProxyType(obs))
            self._observations[point.id] = obs
            self._points[point.id] = point

    def add_observations(self, point_ids: I64, keyframe_id: int, feature_indices: I64) -> None:
        ids = np.asarray(point_ids, np.int64).reshape(-1)
        feats = np.asarray(feature_indices, np.int64).reshape(-1)
        if ids.size != feats.size:
            raise ValueError(f"add_observations: {ids.size} points but {feats.size} feature indices")
        if not ids.size:
            return
        observations = self._observations
        id_list, feat_list = ids.tolist(), feats.tolist()
        targets = [observations[pid] for pid in id_list]  # KeyError for a point not in the map, as add_observation
        own = self._kf_point_ids[keyframe_id]
        distinct = len(set(id_list)) == len(id_list) and len(set(feat_list)) == len(feat_list)
        if not distinct or any(keyframe_id in obs for obs in targets):
            for pid, feat in zip(id_list, feat_list, strict=True):  # the general rule, one at a time
                self.add_observation(pid, keyframe_id, feat)
            return
        kf = self._keyframes.get(keyframe_id)
        if kf is None or kf.features.bf <= 0.0:
            weights: NDArray[np.int64] | int = 1
        else:
            weights = np.array([observation_weight(kf.features, f) for f in feat_list], np.int64)
        self._table.add(ids, "n_observations", 1)
        self._table.add(ids, "n_observations_orbslam", weights)
        for obs, feat in zip(targets, feat_list, strict=True):
            obs[keyframe_id] = feat
        own[feats] = ids

    def _observation_weight(self, keyframe_id: int, feature_index: int) -> int:
        """ORB-SLAM's MapPoint::AddObservation weight of keypoint ``feature_index`` of a keyframe of this map: 2 when
        it has a right coordinate (stereo / RGB-D: ``nObs += 2`` when mvuRight[idx] >= 0) or is a camera-1 keypoint
        of a two-camera keyframe with a stereo match (observed by both cameras), else 1 (``observation_weight``)."""
        kf = self._keyframes.get(keyframe_id)
        if kf is None or kf.features.bf <= 0.0:
            return 1
        return observation_weight(kf.features, feature_index)

    def _forget_point(self, point_id: int) -> dict[int, int]:
        del self._points[point_id]
        self._table.erase(point_id)
        return self._observations.pop(point_id)

    def remove_point(self, point_id: int) -> None:
        obs = self._forget_point(point_id)
        for kf_id, idx in obs.items():
            own = self._kf_point_ids.get(kf_id)
            if own is not None and own[idx] == point_id:
                own[idx] = -1

    def remove_keyframe(self, keyframe_id: int) -> None:
        own = self._kf_point_ids[keyframe_id]
        for idx, pid in enumerate(own.tolist()):
            if pid < 0:
                continue
            obs = self._observations.get(pid)
            if obs is None:
                continue
            if obs.pop(keyframe_id, None) is not None:
                self._table.increment(pid, "n_observations", -1)
                self._table.increment(pid, "n_observations_orbslam", -self._observation_weight(keyframe_id, idx))
            if not obs:
                self._forget_point(pid)
            elif self._points[pid].ref_kf_id == keyframe_id:
                replace_fields(self._points[pid], ref_kf_id=min(obs))
            own[idx] = -1
        self._tree.remove(keyframe_id, self._covisibility)
        self._covisibility.remove(keyframe_id)
        self._loop_edges = {e for e in self._loop_edges if keyframe_id not in e}
        del self._keyframes[keyframe_id]
        del self._kf_point_ids[keyframe_id]
        self._erased_keyframes.add(keyframe_id)

    def add_observation(self, point_id: int, keyframe_id: int, feature_index: int) -> None:
        obs = self._observations[point_id]
        own = self._kf_point_ids[keyframe_id]
        if keyframe_id not in obs:
            self._table.increment(point_id, "n_observations", 1)
        else:  # the keyframe observes it at another keypoint now: its weight may change
            previous = self._observation_weight(keyframe_id, obs[keyframe_id])
            self._table.increment(point_id, "n_observations_orbslam", -previous)
        self._table.increment(point_id, "n_observations_orbslam", self._observation_weight(keyframe_id, feature_index))
        obs[keyframe_id] = feature_index
        own[feature_index] = point_id

    def remove_observation(self, point_id: int, keyframe_id: int) -> None:
        obs = self._observations[point_id]
        idx = obs.pop(keyframe_id, None)
        if idx is not None:
            self._table.increment(point_id, "n_observations", -1)
            self._table.increment(point_id, "n_observations_orbslam", -self._observation_weight(keyframe_id, idx))
        own = self._kf_point_ids.get(keyframe_id)
        if idx is not None and own is not None and own[idx] == point_id:
            own[idx] = -1
        if len(obs) < 2:
            self.remove_point(point_id)
        elif self._points[point_id].ref_kf_id == keyframe_id:
            replace_fields(self._points[point_id], ref_kf_id=min(obs))

    def replace_point(self, old_id: int, new_id: int) -> None:
        if old_id == new_id:
            raise ValueError(f"replace_point: map point {old_id} cannot replace itself")
        old_obs = self._observations[old_id]
        new_obs = self._observations[new_id]
        # add_observation(new_id, kf_id, feat) for each keyframe new does not see, its two counters summed into one
        # write each (integer sums: the same counts)
        added = 0
        weight = 0
        for kf_id, feat in sorted(old_obs.items()):
            own = self._kf_point_ids[kf_id]
            own[feat] = -1
            if kf_id not in new_obs:
                weight += self._observation_weight(kf_id, feat)
                new_obs[kf_id] = feat
                own[feat] = new_id
                added += 1
        if added:
            self._table.increment(new_id, "n_observations", added)
            self._table.increment(new_id, "n_observations_orbslam", weight)
        with self._counter_lock:
            for name in ("n_visible", "n_found"):
                self._table.increment(new_id, name, self._table.value(old_id, name))
        self._forget_point(old_id)

    def set_keyframe_pose(self, keyframe_id: int, T_c_w: NDArray[np.float64]) -> None:
        replace_fields(self._keyframes[keyframe_id], T_c_w=frozen_copy(T_c_w, np.float64))

    def set_keyframe_poses(self, keyframe_ids: Iterable[int], T_c_w: NDArray[np.float64]) -> None:
        ids = list(keyframe_ids)
        if len(ids) != len(T_c_w):
            raise ValueError(f"set_keyframe_poses: {len(ids)} keyframes but {len(T_c_w)} poses")
        for kf_id, T in zip(ids, T_c_w, strict=True):
            self.set_keyframe_pose(kf_id, T)

    def set_keyframe_bow(self, keyframe_id: int, bow: BowDescription) -> None:
        replace_fields(self._keyframes[keyframe_id], bow=bow)

    def assign_points(self, point_ids: I64, attribute: str, values: NDArray[Any]) -> None:
        if attribute not in _ASSIGNABLE:
            raise KeyError(f"assign_points: {attribute!r} is not an assignable point attribute")
        ids = np.asarray(point_ids, np.int64).reshape(-1)
        if len(ids) != len(values):
            raise ValueError(f"assign_points: {len(ids)} points but {len(values)} values of {attribute}")
        if not ids.size:
            return
        own = np.array(values, copy=True)
        own.setflags(write=False)  # each point gets a read-only row of this private copy
        points = self._points
        try:
            targets = [points[pid].__dict__ for pid in ids.tolist()]
        except KeyError as exc:
            raise ValueError(f"assign_points: map point {exc.args[0]} is not in this map") from None
        # the points whose value changes, bit for bit (the table mirrors every point: a point whose row holds the new
        # bits already holds the new value; -0.0 and 0.0 or two NaNs of other bits are a change): the others keep
        # theirs (equal in every bit), a Python step saved per point (refreshes rewrite many unchanged descriptors)
        new = own
        stored = self._table.rows(ids, attribute)
        if stored.shape == own.shape and stored.dtype == own.dtype:
            changed = np.flatnonzero(~_same_bits(stored, own))
            if changed.size < ids.size:
                targets = [targets[i] for i in changed.tolist()]
                new = own[changed]
                new.setflags(write=False)
        # a scalar attribute as a Python float (tolist: what .item() gives per row), an array attribute as a row view
        for fields, value in zip(targets, new.tolist() if new.ndim == 1 else list(new), strict=True):
            fields[attribute] = value
        self._table.assign(ids, attribute, own)

    def increase_visible(self, point_ids: I64, n: int = 1) -> None:
        with self._counter_lock:
            self._table.add(np.asarray(point_ids, np.int64), "n_visible", n)

    def increase_found(self, point_ids: I64, n: int = 1) -> None:
        with self._counter_lock:
            self._table.add(np.asarray(point_ids, np.int64), "n_found", n)

    # ---- mutations: graphs -----------------------------------------------------------------------------

    def update_connections(self, keyframe_id: int) -> None:
        shared = self.shared_point_counts(keyframe_id)
        self._covisibility.update_connections(keyframe_id, shared, self.covisibility_min_shared)
        if keyframe_id not in self._tree:
            # ORB-SLAM KeyFrame::UpdateConnections: the map's initial keyframe gets no parent (mnId != InitKFid),
            # else the two keyframes of the initialization would be each other's parent
            neighbors = self._covisibility.neighbors(keyframe_id)
            root = keyframe_id == self._first_keyframe or not neighbors
            self._tree.add(keyframe_id, None if root else neighbors[0])

    def add_loop_edge(self, a: int, b: int) -> None:
        self._loop_edges.add((min(a, b), max(a, b)))

    # ---- restoring a saved map -------------------------------------------------------------------------

    def restore(self, contents: MapContents) -> None:
        if self._keyframes or self._points or self._erased_keyframes or not self._table.is_empty():
            raise ValueError("restore: the map is not empty (a saved map is restored into a new store)")
        check_contents(contents, self._ids)
        self._put_entities(contents)
        for kf_id, parent in contents.tree.items():
            self._tree.add(kf_id, parent)
        self._loop_edges = {(min(a, b), max(a, b)) for a, b in contents.loop_edges}
        self._first_keyframe = contents.first_keyframe_id
        self._epoch = int(contents.epoch)

    def add_contents(self, contents: MapContents, roots_parent: int | None = None, checked: bool = False) -> None:
        if not checked:
            check_contents(contents, self._ids)
        taken = [kf.id for kf in contents.keyframes if kf.id in self._keyframes or kf.id in self._erased_keyframes]
        pids = np.array([p.id for p in contents.points], np.int64)
        if pids.size and (any(int(p) in self._points for p in pids.tolist()) or self._table.state(pids).any()):
            taken.append(-1)
        if taken:
            raise ValueError("add_contents: ids of the contents are already in this map or were erased from it")
        if roots_parent is not None and roots_parent not in self._keyframes:
            raise ValueError(f"add_contents: the roots' parent {roots_parent} is not a keyframe of this map")
        self._put_entities(contents)
        for kf_id, parent in contents.tree.items():
            self._tree.add(kf_id, roots_parent if parent is None else parent)
        self._loop_edges |= {(min(a, b), max(a, b)) for a, b in contents.loop_edges}
        if self._origin is not None and contents.keyframes:
            self._origin = min(self._origin, min(kf.id for kf in contents.keyframes))

    def _put_entities(self, contents: MapContents) -> None:
        """The keyframes, points (observations, counters) and covisibility edges of checked ``contents``."""
        for kf in contents.keyframes:
            own = np.array(kf.point_ids, np.int64)
            restored = KeyFrame(kf.id, kf.frame_index, kf.timestamp_s, kf.T_c_w, kf.camera, kf.features, own, kf.bow)
            replace_fields(restored, point_ids=frozen_view(own))
            self._keyframes[kf.id] = restored
            self._kf_point_ids[kf.id] = own
            self._covisibility.add_node(kf.id)
        for point in contents.points:
            pid = point.id
            restored_point = MapPoint(
                pid, point.xyz_w, point.descriptor, point.ref_kf_id, point.first_kf_id, point.normal_w,
                point.d_min_m, point.d_max_m,
            )  # fmt: skip
            obs = dict(point.observations)
            replace_fields(restored_point, observations=MappingProxyType(obs))
            self._observations[pid] = obs
            self._points[pid] = restored_point
        if contents.points:
            pts = contents.points
            rows = {name: np.array([getattr(p, name) for p in pts]) for name, _, _ in SYNCED_ATTRIBUTES}
            rows["n_visible"] = contents.n_visible
            rows["n_found"] = contents.n_found
            rows["n_observations"] = np.array([len(p.observations) for p in pts], np.int64)
            rows["n_observations_orbslam"] = np.array(
                [sum(self._observation_weight(k, i) for k, i in p.observations.items()) for p in pts], np.int64
            )
            self._table.put_many(np.array([p.id for p in pts], np.int64), rows)
        for a, b, w in contents.covisibility.tolist():
            self._covisibility.set_edge(a, b, w)


def _same_bits(a: NDArray[Any], b: NDArray[Any]) -> NDArray[np.bool_]:
    """(P,) bool: row p of ``a`` and of ``b`` (same shape and dtype, (P,) or (P, ...)) hold the same bytes."""
    a2 = np.ascontiguousarray(a).reshape(a.shape[0], -1).view(np.uint8)
    b2 = np.ascontiguousarray(b).reshape(b.shape[0], -1).view(np.uint8)
    return np.asarray(np.all(a2 == b2, axis=1))


if TYPE_CHECKING:  # mypy checks that the class implements the protocol
    _implements: MapStore = InMemoryMapStore()
