"""The MapStore protocol: everything the pipeline asks of a map, and the only way the map changes.

Re-exported by slamkit.interfaces (the registry checks a ``map=`` component against it). The pipeline, the
runtime and app.py see a map only through this protocol; tests/contracts/test_map_store_contract.py holds every
registered store to the behaviour documented here.

Entities (slamkit.map.entities KeyFrame, MapPoint) are plain data owned by the store and read-only to everyone
else: their arrays are not writeable, a point's observations are a read-only mapping, and each mutation below
is a store method. Ids come from the store's IdAllocator (slamkit/map/ids.py), which several stores (the maps of
an Atlas) may share: ids are monotonic, unique across those stores and never reused.

Locking: callers take ``read()`` around reads and ``write()`` around mutations when several threads use the
map (the sequential runner needs no locking, but taking the lock is cheap). The one exception is the
visible/found counters: tracking increases them under the read lock, so ``increase_visible`` /
``increase_found`` are safe with other readers.
"""

from __future__ import annotations

from collections.abc import Iterable
from contextlib import AbstractContextManager
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from slamkit.interfaces import BowDescription
    from slamkit.map.entities import KeyFrame, MapPoint
    from slamkit.map.ids import IdAllocator
    from slamkit.map.mapfile_contents import MapContents

I64 = NDArray[np.int64]


@runtime_checkable
class CovisibilityGraphView(Protocol):
    """The covisibility graph (ORB-SLAM III-D), read-only: an edge joins two keyframes sharing at least the store's
    ``covisibility_min_shared`` map points (15), weighted by the number of shared points. Orders are
    deterministic: best first, ties by lower id."""

    def __contains__(self, kf_id: object) -> bool: ...

    def weight(self, a: int, b: int) -> int:
        """Shared points of the edge a-b, 0 when there is none."""
        ...

    def neighbors(self, kf_id: int, min_weight: int = 0) -> list[int]:
        """Neighbours with weight >= min_weight, best first (ties: lower id first); a new list."""
        ...

    def best_neighbors(self, kf_id: int, n: int) -> list[int]:
        """The first n of ``neighbors(kf_id)``."""
        ...

    def edges(self) -> list[tuple[int, int, int]]:
        """Every edge once as (a, b, weight), a < b, sorted."""
        ...


@runtime_checkable
class SpanningTreeView(Protocol):
    """The spanning tree of keyframes (III-D), read-only."""

    def __contains__(self, kf_id: object) -> bool: ...

    def parent(self, kf_id: int) -> int | None:
        """The keyframe's parent (None for the root or a keyframe not in the tree)."""
        ...

    def children(self, kf_id: int) -> list[int]:
        """The keyframe's children, sorted (empty for a leaf or a keyframe not in the tree)."""
        ...

    def edges(self) -> list[tuple[int, int]]:
        """Every (parent, child) edge, sorted."""
        ...


@runtime_checkable
class MapStore(Protocol):
    """One map: keyframes, map points, the covisibility graph, the spanning tree and loop edges, behind one
    readers-writer lock. Shapes: ``point_ids`` (K,) int64; poses (4, 4) or (K, 4, 4) float64 ``T_c_w`` (world ->
    camera); positions m in the world frame."""

    # ---- locking, epoch, ids ------------------------------------------------------------------------

    @property
    def epoch(self) -> int:
        """Bumped by every large correction (loop closure, map merge) so tracking can notice it."""
        ...

    def bump_epoch(self) -> int:
        """epoch += 1; returns the new epoch."""
        ...

    def read(self) -> AbstractContextManager[None]:
        """Shared lock: many readers at a time, no writer."""
        ...

    def write(self) -> AbstractContextManager[None]:
        """Exclusive lock (not re-entrant)."""
        ...

    @property
    def ids(self) -> IdAllocator:
        """Where the store's ids come from (possibly shared with other stores)."""
        ...

    def new_keyframe_id(self) -> int:
        """A fresh keyframe id from ``ids``."""
        ...

    def new_point_id(self) -> int:
        """A fresh map point id from ``ids``."""
        ...

    # ---- entities (read) --------------------------------------------------------------------------------

    def keyframe_ids(self) -> list[int]:
        """Ids of the keyframes in the map, sorted."""
        ...

    def point_ids(self) -> list[int]:
        """Ids of the map points, sorted."""
        ...

    def n_keyframes(self) -> int: ...

    def n_points(self) -> int: ...

    def origin_keyframe_id(self) -> int:
        """The smallest keyframe id in the map (the origin BA holds fixed); ValueError when the map is empty."""
        ...

    def has_keyframe(self, keyframe_id: int) -> bool: ...

    def has_point(self, point_id: int) -> bool: ...

    def has_points(self, point_ids: I64) -> NDArray[np.bool_]:
        """(K,) bool: which of any ids (negative ones included) name a point in the map."""
        ...

    def get_keyframe(self, keyframe_id: int) -> KeyFrame:
        """The keyframe (KeyError when absent); read-only, it follows the store's changes."""
        ...

    def get_point(self, point_id: int) -> MapPoint:
        """The map point (KeyError when absent); read-only, it follows the store's changes."""
        ...

    def get_points(self, point_ids: Iterable[int]) -> list[MapPoint]:
        """The points among ``point_ids`` still in the map, in the given order (erased ids skipped)."""
        ...

    def point_rows(self, point_ids: I64, attribute: str) -> NDArray[Any]:
        """(K, ...) a copy of one attribute of K points that are all in the map, in one array operation:
        "xyz_w" (K, 3) m, "normal_w" (K, 3), "d_min_m" / "d_max_m" (K,) m, "descriptor" (K, B) uint8, and the
        counters "n_visible" / "n_found" (K,) int64 (VI-B), "n_observations" (K,) int64 and
        "n_observations_orbslam" (K,) int64 (ORB-SLAM's MapPoint::Observations(): an observation whose keyframe
        keypoint has a right coordinate, stereo or RGB-D, counts 2; optional: without it, a KeyError, the pipeline
        counts from the observations). Equal to the entities' attributes after every mutation."""
        ...

    # ---- graphs (read) ----------------------------------------------------------------------------------

    @property
    def covisibility(self) -> CovisibilityGraphView: ...

    @property
    def spanning_tree(self) -> SpanningTreeView: ...

    def loop_edges(self) -> list[tuple[int, int]]:
        """Loop-closure edges (a, b), a < b, sorted."""
        ...

    # ---- mutations --------------------------------------------------------------------------------------

    def add_keyframe(self, keyframe: KeyFrame) -> None:
        """Insert a keyframe whose id came from ``ids``. Each entry of its point_ids naming a point in the map
        becomes an observation (both directions), in feature order; entries naming a point not in the map, or a
        point an earlier feature of this keyframe already observes, become -1. ValueError for an id already
        used."""
        ...

    def add_point(self, point: MapPoint) -> None:
        """Insert a map point (id from ``ids``, no observations yet: add them with add_observation); its counters
        start at n_visible = n_found = 1. ValueError for an id already used or a descriptor width unlike the
        map's."""
        ...

    def remove_point(self, point_id: int) -> None:
        """Erase a point and every keyframe's entry of it (culling)."""
        ...

    def remove_keyframe(self, keyframe_id: int) -> None:
        """Erase a keyframe (culling): its observations (a point whose reference keyframe it was gets the
        smallest remaining observer; a point left unobserved is erased), its covisibility edges, its loop edges and
        its spanning-tree node (children re-parented to the best-connected candidate, ORB-SLAM SetBadFlag)."""
        ...

    def add_observation(self, point_id: int, keyframe_id: int, feature_index: int) -> None:
        """Feature ``feature_index`` of the keyframe observes the point (both directions)."""
        ...

    def remove_observation(self, point_id: int, keyframe_id: int) -> None:
        """Forget that a keyframe observes a point (both directions); a point left with fewer than two
        observations is erased, else its reference keyframe moves to its smallest observer if it was this one
        (ORB-SLAM MapPoint::EraseObservation)."""
        ...

    def replace_point(self, old_id: int, new_id: int) -> None:
        """ORB-SLAM MapPoint::Replace: every observation of ``old`` moves to ``new`` (in keyframe-id order; a
        keyframe already observing ``new`` just loses its entry of ``old``), old's visible/found counters are
        added to new's, and ``old`` is erased. Leaves new's descriptor and normal to the caller."""
        ...

    def set_keyframe_pose(self, keyframe_id: int, T_c_w: NDArray[np.float64]) -> None:
        """T_c_w: (4, 4) the keyframe's new pose, world -> camera (copied)."""
        ...

    def set_keyframe_poses(self, keyframe_ids: Iterable[int], T_c_w: NDArray[np.float64]) -> None:
        """T_c_w: (K, 4, 4) new poses of K keyframes in the map (bundle adjustment, loop correction)."""
        ...

    def set_keyframe_bow(self, keyframe_id: int, bow: BowDescription) -> None:
        """The keyframe's bag of words (ORB-SLAM ProcessNewKeyFrame ComputeBoW)."""
        ...

    def assign_points(self, point_ids: I64, attribute: str, values: NDArray[Any]) -> None:
        """values[i] becomes attribute ``attribute`` of point point_ids[i] (points in the map), in bulk:
        "xyz_w" (K, 3) m, "normal_w" (K, 3), "d_min_m" / "d_max_m" (K,) m or "descriptor" (K, B) uint8."""
        ...

    def increase_visible(self, point_ids: I64, n: int = 1) -> None:
        """n_visible += n for each listed point (an id listed twice counts twice; ORB-SLAM IncreaseVisible).
        Safe under the read lock: tracking calls it there for thousands of points per frame."""
        ...

    def increase_found(self, point_ids: I64, n: int = 1) -> None:
        """n_found += n, as ``increase_visible`` (ORB-SLAM IncreaseFound)."""
        ...

    def update_connections(self, keyframe_id: int) -> None:
        """Recompute a keyframe's covisibility edges from its shared points (at least ``covisibility_min_shared``,
        else the single best so it is never isolated); a keyframe entering the spanning tree gets as parent the
        keyframe it shares most points with, except the map's first keyframe (the one added to the empty map: after
        a reset, the next one), the tree's root
        (ORB-SLAM KeyFrame::UpdateConnections, ``mnId != InitKFid``): the tree never has a cycle."""
        ...

    def add_loop_edge(self, a: int, b: int) -> None:
        """Record a loop-closure edge between keyframes a and b."""
        ...

    # ---- restoring a saved map ----------------------------------------------------------------------------

    def restore(self, contents: MapContents) -> None:
        """Fill this *empty* store with a saved map (slamkit.map.mapfile_contents.MapContents, e.g. read back from a
        map file), entities keeping their ids: the keyframes with their point_ids and bags of words, the points with
        their observations (in the saved order) and visible/found counters, the covisibility edges with their saved
        weights, the spanning-tree parents, the loop edges, the first keyframe (the root) and the epoch. Afterwards
        every read above answers as it did on the saved map (``read_map_contents`` gives the same contents) and the
        mutations go on from there. The store's ``ids`` must already have issued every id of ``contents`` (the
        caller builds the allocator from the saved one). ValueError, before anything changes, when the store is not
        empty or ``contents`` is inconsistent (``mapfile_contents.check_contents``)."""
        ...

    def add_contents(self, contents: MapContents, roots_parent: int | None = None, checked: bool = False) -> None:
        """Add another map's entities to this one at once (map merging, slamkit/pipeline/map_merging.py), as they are
        in ``contents`` (ids issued by this store's allocator, none of them in this map nor erased from it): the
        keyframes with their point_ids and bags of words, the points with their observations (by keyframes of
        ``contents``) and visible/found counters, the covisibility edges with their weights, the spanning-tree
        parents, where a root of ``contents`` gets ``roots_parent`` (a keyframe of this map; None: it stays a root),
        and the loop edges. This map's first keyframe and epoch stay. Afterwards the reads answer for both maps'
        entities as each answered before. ValueError, before anything changes, when ``contents`` is inconsistent
        (``mapfile_contents.check_contents``; ``checked``: the caller ran it already, against this map's allocator, e.g.
        before taking the write lock), an id is taken or ``roots_parent`` is not in this map."""
        ...
