"""MapContents: everything one map holds, as plain data — what a map file saves and ``MapStore.restore`` puts back.

A map's state is more than its entities: the visible/found counters (ORB-SLAM VI-B), the covisibility weights as
they were last computed (``update_connections`` recomputes a keyframe's edges only when asked, so they can differ
from a count of today's shared points), the spanning tree's parents (chosen when each keyframe arrived, then
re-parented by culling), the loop edges, the map's first keyframe (the root ``update_connections`` gives no
parent) and the epoch. :func:`read_map_contents` reads all of it through the MapStore protocol (any store);
``MapStore.restore`` fills an empty store with it so that the restored map answers every protocol read as the
original did and goes on behaving the same (slamkit/map/protocol.py).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from slamkit.interfaces import BowDescription
from slamkit.map.entities import KeyFrame, MapPoint

if TYPE_CHECKING:
    from slamkit.map.ids import IdAllocator
    from slamkit.map.protocol import MapStore

I64 = NDArray[np.int64]


@dataclass(frozen=True, eq=False)
class MapContents:
    """One map as plain data (a snapshot: nothing here is shared with a live store).

    keyframes: ascending ids; each keyframe's ``point_ids`` (N,) names the map point each feature observes (-1 none)
        and ``bow`` its bag of words (None if it was never described).
    points: ascending ids; each point's ``observations`` keyframe id -> feature index, in the store's order.
    n_visible / n_found: (P,) int64 the points' counters (VI-B), in the order of ``points``.
    covisibility: (E, 3) int64 rows (a, b, weight), a < b, sorted: the covisibility graph as the store holds it.
    tree: keyframe id -> parent id (None: a root) for every keyframe in the spanning tree.
    loop_edges: (a, b) pairs, a < b, sorted.
    first_keyframe_id: the map's first keyframe, the spanning tree's root (None for an empty map).
    epoch: the map's epoch (bumped by loop corrections).
    """

    keyframes: tuple[KeyFrame, ...]
    points: tuple[MapPoint, ...]
    n_visible: I64
    n_found: I64
    covisibility: I64
    tree: Mapping[int, int | None]
    loop_edges: tuple[tuple[int, int], ...]
    first_keyframe_id: int | None
    epoch: int = 0


def read_map_contents(store: MapStore) -> MapContents:
    """Everything ``store`` holds, through the MapStore protocol (the caller holds the store's read lock, or no other
    thread changes the map). The entities are copies: the snapshot does not follow later changes.

    The first keyframe is taken to be the smallest keyframe id (ids are monotonic, so the map's first keyframe has
    it; after it was culled, the smallest remaining one stands in for it: only a keyframe not yet in the spanning
    tree asks who the root is)."""
    kf_ids = store.keyframe_ids()
    keyframes = tuple(_copy_keyframe(store.get_keyframe(k)) for k in kf_ids)
    pids = np.array(store.point_ids(), np.int64)
    points = tuple(_copy_point(store.get_point(int(p))) for p in pids.tolist())
    if pids.size:
        n_visible = np.asarray(store.point_rows(pids, "n_visible"), np.int64).copy()
        n_found = np.asarray(store.point_rows(pids, "n_found"), np.int64).copy()
    else:
        n_visible = n_found = np.zeros(0, np.int64)
    edges = store.covisibility.edges()
    covisibility = np.array(edges, np.int64).reshape(len(edges), 3)
    tree = store.spanning_tree
    parents = {k: tree.parent(k) for k in kf_ids if k in tree}
    return MapContents(
        keyframes=keyframes,
        points=points,
        n_visible=n_visible,
        n_found=n_found,
        covisibility=covisibility,
        tree=parents,
        loop_edges=tuple((int(a), int(b)) for a, b in store.loop_edges()),
        first_keyframe_id=kf_ids[0] if kf_ids else None,
        epoch=int(store.epoch),
    )


def _copy_keyframe(kf: KeyFrame) -> KeyFrame:
    return KeyFrame(kf.id, kf.frame_index, kf.timestamp_s, kf.T_c_w, kf.camera, kf.features, kf.point_ids, kf.bow)


def _copy_point(p: MapPoint) -> MapPoint:
    return MapPoint(
        p.id, p.xyz_w, p.descriptor, p.ref_kf_id, p.first_kf_id, p.normal_w, p.d_min_m, p.d_max_m, dict(p.observations)
    )


def check_contents(contents: MapContents, ids: IdAllocator) -> None:
    """ValueError naming the first inconsistency of ``contents`` for a store whose ids come from ``ids``: an id the
    allocator has not issued or given twice, observations that disagree between a point and its keyframe, counters
    or graphs naming keyframes the map does not hold, a spanning tree with a cycle. ``MapStore.restore`` calls it
    before changing anything."""
    kfs: dict[int, KeyFrame] = {}
    for kf in contents.keyframes:
        if kf.id in kfs:
            raise ValueError(f"keyframe {kf.id} is listed twice")
        if not ids.issued_keyframe(kf.id):
            raise ValueError(f"keyframe {kf.id}: its id was not issued by the map's id allocator")
        if kf.point_ids.shape != (len(kf.features),):
            raise ValueError(f"keyframe {kf.id}: {kf.point_ids.shape} point ids for {len(kf.features)} features")
        kfs[kf.id] = kf
    points: dict[int, MapPoint] = {}
    width: int | None = None
    for p in contents.points:
        if p.id in points:
            raise ValueError(f"map point {p.id} is listed twice")
        if not ids.issued_point(p.id):
            raise ValueError(f"map point {p.id}: its id was not issued by the map's id allocator")
        if width is None:
            width = p.descriptor.shape[0] if p.descriptor.ndim == 1 else -1
        if p.descriptor.shape != (width,) or p.xyz_w.shape != (3,) or p.normal_w.shape != (3,):
            raise ValueError(f"map point {p.id}: malformed position, normal or descriptor")
        for k, feat in p.observations.items():
            observer = kfs.get(k)
            if observer is None or not 0 <= feat < len(observer.point_ids) or int(observer.point_ids[feat]) != p.id:
                raise ValueError(f"map point {p.id}: observation by keyframe {k} feature {feat} not in that keyframe")
        points[p.id] = p
    for kf in kfs.values():
        for feat in np.flatnonzero(kf.point_ids >= 0).tolist():
            p_obs = points.get(int(kf.point_ids[feat]))
            if p_obs is None or p_obs.observations.get(kf.id) != feat:
                raise ValueError(f"keyframe {kf.id}: feature {feat} names map point {kf.point_ids[feat]}, not observed")
    n = len(contents.points)
    if contents.n_visible.shape != (n,) or contents.n_found.shape != (n,):
        raise ValueError(f"{n} map points but {contents.n_visible.shape} / {contents.n_found.shape} counters")
    cov = contents.covisibility
    if cov.ndim != 2 or cov.shape[1] != 3:
        raise ValueError(f"covisibility edges of shape {cov.shape}, expected (E, 3)")
    for a, b, w in cov.tolist():
        if a == b or a not in kfs or b not in kfs or w <= 0:
            raise ValueError(f"covisibility edge ({a}, {b}, {w}) does not join two keyframes of the map")
    for k, parent in contents.tree.items():
        if k not in kfs or (parent is not None and parent not in kfs):
            raise ValueError(f"spanning tree edge ({parent}, {k}) names a keyframe not in the map")
    for k in contents.tree:
        seen = {k}
        up = contents.tree.get(k)
        while up is not None:
            if up in seen:
                raise ValueError(f"the spanning tree has a cycle through keyframe {k}")
            seen.add(up)
            up = contents.tree.get(up)
    for a, b in contents.loop_edges:
        if a not in kfs or b not in kfs:
            raise ValueError(f"loop edge ({a}, {b}) names a keyframe not in the map")
    if contents.first_keyframe_id is None and kfs:
        raise ValueError("a map with keyframes needs its first keyframe")


def differences(a: MapContents, b: MapContents, limit: int = 10) -> list[str]:
    """What differs between two maps' contents, exactly (bit for bit: arrays by value and dtype, dict orders
    included), as up to ``limit`` lines; empty when they are identical. Cameras are compared by their parameters."""
    out: list[str] = []

    def note(text: str) -> bool:
        out.append(text)
        return len(out) >= limit

    if [k.id for k in a.keyframes] != [k.id for k in b.keyframes]:
        return ["keyframe ids differ"]
    if [p.id for p in a.points] != [p.id for p in b.points]:
        return ["map point ids differ"]
    for ka, kb in zip(a.keyframes, b.keyframes, strict=True):
        for name in ("frame_index", "timestamp_s"):
            if getattr(ka, name) != getattr(kb, name) and note(f"keyframe {ka.id}: {name}"):
                return out
        for name in ("T_c_w", "point_ids"):
            if not _same_array(getattr(ka, name), getattr(kb, name)) and note(f"keyframe {ka.id}: {name}"):
                return out
        if _camera_key(ka.camera) != _camera_key(kb.camera) and note(f"keyframe {ka.id}: camera"):
            return out
        fa, fb = ka.features, kb.features
        for name in fa.__dataclass_fields__:
            va, vb = getattr(fa, name), getattr(fb, name)
            if name == "camera_2":  # a rig's second camera: by its parameters, as the keyframe's camera
                same = _camera_key(va) == _camera_key(vb)
            else:
                same = _same_array(va, vb) if isinstance(va, np.ndarray) else va == vb
            if not same and note(f"keyframe {ka.id}: features.{name}"):
                return out
        if not _same_bow(ka.bow, kb.bow) and note(f"keyframe {ka.id}: bow"):
            return out
    for pa, pb in zip(a.points, b.points, strict=True):
        for name in ("ref_kf_id", "first_kf_id", "d_min_m", "d_max_m"):
            if getattr(pa, name) != getattr(pb, name) and note(f"map point {pa.id}: {name}"):
                return out
        for name in ("xyz_w", "normal_w", "descriptor"):
            if not _same_array(getattr(pa, name), getattr(pb, name)) and note(f"map point {pa.id}: {name}"):
                return out
        if list(pa.observations.items()) != list(pb.observations.items()) and note(f"map point {pa.id}: observations"):
            return out
    for name in ("n_visible", "n_found", "covisibility"):
        if not _same_array(getattr(a, name), getattr(b, name)) and note(name):
            return out
    if dict(a.tree) != dict(b.tree) and note("spanning tree"):
        return out
    for name in ("loop_edges", "first_keyframe_id", "epoch"):
        if getattr(a, name) != getattr(b, name) and note(name):
            return out
    return out


def _same_array(x: object, y: object) -> bool:
    ax, ay = np.asarray(x), np.asarray(y)
    return ax.dtype == ay.dtype and ax.shape == ay.shape and ax.tobytes() == ay.tobytes()


def _same_bow(x: BowDescription | None, y: BowDescription | None) -> bool:
    if x is None or y is None:
        return x is y
    if list(x.words.items()) != list(y.words.items()) or list(x.direct_index) != list(y.direct_index):
        return False
    return all(_same_array(v, y.direct_index[k]) for k, v in x.direct_index.items())


def _camera_key(camera: object) -> object:
    to_dict = getattr(camera, "to_dict", None)
    return to_dict() if callable(to_dict) else id(camera)


__all__ = ["MapContents", "check_contents", "differences", "read_map_contents"]
