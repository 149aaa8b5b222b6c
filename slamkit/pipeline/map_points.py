"""Map point properties derived from its observations (ORB-SLAM sec. III-C): mean viewing direction,
scale-invariance distances, representative descriptor, and the pyramid level predicted at a distance.

``refresh_points`` recomputes them for many points at once: the observations are gathered once (grouped by
keyframe, so each keyframe's arrays are indexed with one numpy call) and one numba pass (GIL released) does
the arithmetic, instead of a numpy round trip per point. ``update_normal_and_depth`` and
``compute_distinctive_descriptor`` are the one-point forms of the same kernel.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from itertools import chain
from operator import attrgetter, methodcaller
from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

from slamkit.geometry.se3 import invert_T
from slamkit.interfaces import MapStore
from slamkit.map.entities import KeyFrame, MapPoint, observation_weight
from slamkit.pipeline.matching import row_distance

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
U8 = NDArray[np.uint8]


@numba.njit(cache=True, nogil=True, inline="always")
def _normal_and_depth(
    q: int,
    s: int,
    e: int,
    xyz: F64,
    center: F64,
    ref_row: I64,
    level: I64,
    scale_factor: F64,
    n_levels: I64,
    normal: F64,
    has_normal: NDArray[np.bool_],
    d_min: F64,
    d_max: F64,
) -> None:  # pragma: no cover - compiled
    """Point q's normal, has_normal, d_min and d_max (see :func:`_refresh_kernel`) from its observations s:e."""
    sx = 0.0
    sy = 0.0
    sz = 0.0
    count = 0
    for a in range(s, e):
        vx = xyz[q, 0] - center[a, 0]
        vy = xyz[q, 1] - center[a, 1]
        vz = xyz[q, 2] - center[a, 2]
        nv = np.sqrt(vx * vx + vy * vy + vz * vz)
        if nv > 0.0:
            sx += vx / nv
            sy += vy / nv
            sz += vz / nv
            count += 1
    if count:
        mx, my, mz = sx / count, sy / count, sz / count
        nm = np.sqrt(mx * mx + my * my + mz * mz)
        if nm > 0.0:
            mx, my, mz = mx / nm, my / nm, mz / nm
        normal[q, 0] = mx
        normal[q, 1] = my
        normal[q, 2] = mz
        has_normal[q] = True
    r = ref_row[q]
    if r >= 0:
        vx = xyz[q, 0] - center[r, 0]
        vy = xyz[q, 1] - center[r, 1]
        vz = xyz[q, 2] - center[r, 2]
        dist = np.sqrt(vx * vx + vy * vy + vz * vz)
        d_max[q] = dist * scale_factor[q] ** level[r]
        d_min[q] = d_max[q] / scale_factor[q] ** (n_levels[q] - 1)


@numba.njit(cache=True, nogil=True)
def _refresh_kernel(
    xyz: F64,
    ptr: I64,
    center: F64,
    desc64: NDArray[np.uint64],
    ref_row: I64,
    level: I64,
    scale_factor: F64,
    n_levels: I64,
    normals: bool = True,
    descriptors: bool = True,
) -> tuple[F64, NDArray[np.bool_], F64, F64, I64]:  # pragma: no cover - compiled
    """Per point q (observations ptr[q]:ptr[q+1], in keyframe-id order):

    -> normal (P, 3) and has_normal (P,): mean of the unit vectors camera centre -> point, normalised;
       d_min, d_max (P,) m from the reference observation ref_row[q] (NaN when it has none);
       best (P,) the observation row with the least median Hamming distance to the others (first on ties),
       -1 when the point has no observation. A row whose median cannot beat the best so far (counted, not sorted)
       is skipped: the same ``best`` as sorting every row.

    normals=False leaves normal / has_normal / d_min / d_max at zero / False / NaN (``center`` and ``ref_row`` are
    not read); descriptors=False leaves best at -1 (``desc64`` is not read): the caller does not use them.
    """
    P = ptr.shape[0] - 1
    normal = np.zeros((P, 3))
    has_normal = np.zeros(P, np.bool_)
    d_min = np.full(P, np.nan)
    d_max = np.full(P, np.nan)
    best = np.full(P, -1, np.int64)
    row = np.zeros(64, np.int64)
    dmat = np.zeros((64, 64), np.int64)
    for q in range(P):
        s, e = ptr[q], ptr[q + 1]
        n = e - s
        if normals:
            _normal_and_depth(
                q, s, e, xyz, center, ref_row, level, scale_factor, n_levels, normal, has_normal, d_min, d_max
            )
        if not descriptors:
            continue
        if n == 1:
            best[q] = s
        elif n > 1:
            if row.shape[0] < n:
                row = np.zeros(n, np.int64)
                dmat = np.zeros((n, n), np.int64)
            # the symmetric distance matrix, each pair once
            for a in range(n):
                dmat[a, a] = 0
                for b in range(a + 1, n):
                    d = row_distance(desc64, s + a, desc64, s + b)
                    dmat[a, b] = d
                    dmat[b, a] = d
            lower = (n - 1) // 2
            best_median = np.inf
            for a in range(n):
                if a > 0:
                    # row a's median is at least its lower middle value r[lower], which is >= best_median when at
                    # most ``lower`` of its entries are below best_median: then the row cannot win (strict <), and
                    # one counting pass skips its sort (the rows after the best so far mostly end here)
                    below = 0
                    for b in range(n):
                        if dmat[a, b] < best_median:
                            below += 1
                    if below <= lower:
                        continue
                if n <= 24:  # row a sorted by insertion (short rows: a point's observations)
                    for b in range(n):
                        v = dmat[a, b]
                        k = b
                        while k > 0 and row[k - 1] > v:
                            row[k] = row[k - 1]
                            k -= 1
                        row[k] = v
                else:
                    row[:n] = np.sort(dmat[a, :n])
                median = 0.5 * (row[(n - 1) // 2] + row[n // 2])  # np.median of the row
                if median < best_median:
                    best_median = median
                    best[q] = s + a
    return normal, has_normal, d_min, d_max, best


_OBSERVATIONS = attrgetter("observations")
_VALUES = methodcaller("values")


def unique_point_ids(point_ids: Sequence[I64]) -> I64:
    """The distinct non-negative ids of the arrays ``point_ids`` (keyframes' point_ids, -1 for no point), sorted:
    ``np.unique(np.concatenate(point_ids))`` without its negative entries, by a mark per id up to the largest (no
    sort of the ~25 neighbours' thousands of entries)."""
    if not point_ids:
        return np.zeros(0, np.int64)
    ids = np.concatenate(point_ids).astype(np.int64, copy=False)
    ids = ids[ids >= 0]
    if not ids.size:
        return np.zeros(0, np.int64)
    mark = np.zeros(int(ids.max()) + 1, bool)
    mark[ids] = True
    return np.flatnonzero(mark).astype(np.int64, copy=False)


def flat_observations(points: Sequence[MapPoint]) -> tuple[I64, I64, I64]:
    """Every observation of ``points`` as flat arrays, in each point's observation order (no sorting):
    -> (counts (P,) observations per point, kf (E,) observing keyframe ids, feat (E,) feature indices), the
    observations of point q at rows sum(counts[:q]) : sum(counts[:q + 1]).

    The dictionaries are walked by C iterators (``map``/``chain``), not a Python loop per observation: the
    observation gathers of local mapping (refresh, local BA, culling) read tens of thousands per keyframe."""
    obs = list(map(_OBSERVATIONS, points))
    counts = np.fromiter(map(len, obs), np.int64, count=len(obs))
    E = int(counts.sum())
    kf = np.fromiter(chain.from_iterable(obs), np.int64, count=E)
    feat = np.fromiter(chain.from_iterable(map(_VALUES, obs)), np.int64, count=E)
    return counts, kf, feat


def gather_observations(store: MapStore, point_ids: I64) -> tuple[I64, I64, I64]:
    """:func:`flat_observations` of the points ``point_ids`` (P,), all in the map: through the store's own
    ``flat_observations`` where it has one (InMemoryMapStore: its plain dictionaries, not the points' read-only
    views), else from ``get_points``. -> (counts (P,), kf (E,), feat (E,))."""
    own = getattr(store, "flat_observations", None)
    if own is not None:
        counts, kf, feat = own(point_ids)
        return np.asarray(counts, np.int64), np.asarray(kf, np.int64), np.asarray(feat, np.int64)
    return flat_observations(store.get_points(np.asarray(point_ids, np.int64).tolist()))


def sorted_observations(counts: I64, kf: I64, feat: I64, keep: NDArray[np.bool_] | None = None) -> tuple[I64, I64, I64]:
    """The rows of flat_observations grouped by point and, within a point, in keyframe-id order (the order of
    ``for kf_id in sorted(point.observations)``), only those with ``keep`` (E,) when given.
    -> (point (E',) row of the point in the input, kf (E',), feat (E',))."""
    point = np.repeat(np.arange(counts.size, dtype=np.int64), counts)
    if keep is not None:
        point, kf, feat = point[keep], kf[keep], feat[keep]
    if not kf.size:
        return point, kf, feat
    # one sort on a combined key: a point has one observation per keyframe (the observation mapping is keyed by
    # keyframe id), so the keys are distinct and the order is np.lexsort((kf, point))'s, at a third of its cost
    lo = int(kf.min())
    order = np.argsort(point * (int(kf.max()) - lo + 1) + (kf - lo))
    return point[order], kf[order], feat[order]


class _Gathered:
    """Observations of P points flattened in point order, each point's in keyframe-id order."""

    def __init__(
        self,
        points: Sequence[MapPoint],
        keyframes: Mapping[int, KeyFrame],
        flat: tuple[I64, I64, I64],
        all_present: bool = False,
        normals: bool = True,
        descriptors: bool = True,
        centers_w: Mapping[int, F64] | None = None,
    ) -> None:
        """flat: ``flat_observations(points)``; observers missing from ``keyframes`` are left out (all_present: the
        caller knows every observer is in ``keyframes``). normals=False skips what only the normals and depth ranges
        read (centres, reference rows, pyramids: left at their zero / -1 / one defaults), descriptors=False the
        descriptors' gather (left zero). centers_w: keyframe id -> (3,) m world camera centre to use instead of the
        keyframe's ``center_w`` (a pose about to be written; keyframes not listed keep theirs)."""
        P = len(points)
        counts, kf_all, feat_all = flat
        present = None if all_present else np.isin(kf_all, np.fromiter(keyframes, np.int64, count=len(keyframes)))
        point, kf_a, feat_a = sorted_observations(counts, kf_all, feat_all, present)
        E = kf_a.size
        self.n_observations = counts
        self.ptr = np.zeros(P + 1, np.int64)
        np.cumsum(np.bincount(point, minlength=P), out=self.ptr[1:])
        self.ref_row = np.full(P, -1, np.int64)
        if normals:
            ref_kf = np.fromiter(map(_REF_KF, points), np.int64, count=P)
            is_ref = np.flatnonzero(kf_a == ref_kf[point])  # at most one row per point (one observation per keyframe)
            self.ref_row[point[is_ref]] = is_ref
        self.center = np.zeros((E, 3))
        self.level = np.zeros(E, np.int64)
        self.desc = np.zeros((E if descriptors else 0, 32), np.uint8)
        self.scale_factor = np.ones(P)
        self.n_levels = np.ones(P, np.int64)
        if E:
            # each keyframe's rows gathered into a contiguous slice of the rows sorted by keyframe, then one
            # permutation back to the point-major order (slice writes instead of fancy-index writes per keyframe)
            order = np.argsort(kf_a, kind="stable")
            by_kf = kf_a[order]
            feat_by_kf = feat_a[order]
            starts = np.flatnonzero(np.r_[True, by_kf[1:] != by_kf[:-1]])  # np.unique's return_index on sorted ids
            ids = by_kf[starts]
            bounds = np.append(starts, E)
            observers = [keyframes[k] for k in ids.tolist()]
            level = np.zeros(E, np.int64)
            desc = np.zeros((E if descriptors else 0, observers[0].features.descriptors.shape[1]), np.uint8)
            for i, kf in enumerate(observers):
                lo, hi = bounds[i], bounds[i + 1]
                feats = kf.features
                sel = feat_by_kf[lo:hi]
                if normals:
                    level[lo:hi] = feats.level[sel]
                if descriptors:
                    desc[lo:hi] = feats.descriptors[sel]
            rank = np.empty(E, np.int64)
            rank[order] = np.arange(E)  # row r of the point-major order is row rank[r] of the keyframe order
            if normals:
                centers = np.array(
                    [
                        kf.center_w if centers_w is None or kf.id not in centers_w else centers_w[kf.id]
                        for kf in observers
                    ],
                    np.float64,
                ).reshape(-1, 3)
                self.center = centers[np.repeat(np.arange(ids.size), np.diff(bounds))[rank]]
                self.level = level[rank]
            if descriptors:
                self.desc = desc[rank]
        has_ref = np.flatnonzero(self.ref_row >= 0)
        if has_ref.size:  # the reference keyframe's pyramid (one per point)
            ref_ids, inverse = np.unique(kf_a[self.ref_row[has_ref]], return_inverse=True)
            pyramids = [keyframes[k].features for k in ref_ids.tolist()]
            self.scale_factor[has_ref] = np.array([f.scale_factor for f in pyramids], np.float64)[inverse]
            self.n_levels[has_ref] = np.array([f.n_levels for f in pyramids], np.int64)[inverse]


_REF_KF = attrgetter("ref_kf_id")


class _PairGathered:
    """:class:`_Gathered`'s arrays for new points each observed by exactly two keyframes, built from the two keyframes'
    feature arrays without walking the observation dictionaries."""

    def __init__(self, kf1: KeyFrame, feat1: I64, kf2: KeyFrame, feat2: I64) -> None:
        """Point q is observed by feature feat1[q] of kf1 (its reference keyframe) and feat2[q] of kf2 (P,)."""
        P = feat1.size
        first, second = (kf1, kf2) if kf1.id < kf2.id else (kf2, kf1)  # each point's rows in keyframe-id order
        fa, fb = (feat1, feat2) if first is kf1 else (feat2, feat1)
        self.n_observations = np.full(P, 2, np.int64)
        self.ptr = np.arange(0, 2 * P + 1, 2, dtype=np.int64)
        self.ref_row = self.ptr[:-1] + (0 if first is kf1 else 1)
        self.center = np.empty((2 * P, 3))
        self.center[0::2] = first.center_w
        self.center[1::2] = second.center_w
        self.level = np.empty(2 * P, np.int64)
        self.level[0::2] = first.features.level[fa]
        self.level[1::2] = second.features.level[fb]
        d1, d2 = first.features.descriptors, second.features.descriptors
        self.desc = np.empty((2 * P, d1.shape[1]), np.uint8)
        self.desc[0::2] = d1[fa]
        self.desc[1::2] = d2[fb]
        self.scale_factor = np.full(P, float(kf1.features.scale_factor))
        self.n_levels = np.full(P, int(kf1.features.n_levels), np.int64)


def refresh_new_pairs(store: MapStore, point_ids: I64, kf1: KeyFrame, feat1: I64, kf2: KeyFrame, feat2: I64) -> None:
    """:func:`refresh_points` (normals, depth ranges and descriptors) of points just made from two keyframes: point
    point_ids[q] (P,) is observed by exactly feature feat1[q] of ``kf1``, its reference keyframe, and feat2[q] of
    ``kf2`` (local mapping's triangulation, VI-C). The same kernel on the same numbers as ``refresh_points``, without
    its gather from the observation dictionaries."""
    ids = np.asarray(point_ids, np.int64)
    if not ids.size:
        return
    _apply_ids(store, ids, _PairGathered(kf1, np.asarray(feat1), kf2, np.asarray(feat2)), True, True)


def new_pair_points(point_ids: I64, xyz_w: F64, kf1: KeyFrame, feat1: I64, kf2: KeyFrame, feat2: I64) -> list[MapPoint]:
    """The new map points point_ids[q] at xyz_w[q] (P, 3) m, each to be observed by feature feat1[q] of ``kf1`` (its
    reference and first keyframe) and feat2[q] of ``kf2`` (local mapping's triangulation, VI-C), made with the normal,
    depth range and descriptor ``refresh_new_pairs`` would write once their observations are added: the same kernel
    on the same numbers, without writing four attributes of every point to the map a second time. Not yet in any
    map (MapStore.add_point, then the two observations)."""
    ids = np.asarray(point_ids, np.int64)
    if not ids.size:
        return []
    xyz = np.ascontiguousarray(xyz_w, np.float64)
    g = _PairGathered(kf1, np.asarray(feat1), kf2, np.asarray(feat2))
    normal, has_normal, d_min, d_max, best = _refreshed(xyz, g, True, True)
    desc = g.desc[best]  # each point has two observations: best >= 0
    kf_id = kf1.id
    return [
        MapPoint(pid, xyz[q], desc[q], kf_id, kf_id, normal[q] if has_normal[q] else None, lo, hi)
        for q, (pid, lo, hi) in enumerate(zip(ids.tolist(), d_min.tolist(), d_max.tolist(), strict=True))
    ]


def _refreshed(
    xyz: F64, g: _Gathered | _PairGathered | _FewGathered, normals: bool, descriptors: bool
) -> tuple[F64, NDArray[np.bool_], F64, F64, I64]:
    """``_refresh_kernel`` on the points at ``xyz`` (P, 3) m (world) with their gathered observations ``g`` (rows in
    the points' order): (normal (P, 3), has_normal (P,), d_min (P,) m, d_max (P,) m, best descriptor row (P,))."""
    return _refresh_kernel(
        xyz,
        g.ptr,
        g.center,
        np.ascontiguousarray(g.desc).view(np.uint64),
        g.ref_row,
        g.level,
        g.scale_factor,
        g.n_levels,
        normals,
        descriptors,
    )


def _ids_of(points: Sequence[MapPoint]) -> I64:
    """(P,) the points' ids in order."""
    return np.array([p.id for p in points], np.int64)


def _apply(
    store: MapStore, points: list[MapPoint], g: _Gathered | _FewGathered, normals: bool, descriptors: bool
) -> None:
    """Recompute the points' normals/depth ranges and descriptors and write them to the points' map in bulk
    (store.assign_points)."""
    if not points:
        return
    _apply_ids(store, _ids_of(points), g, normals, descriptors)


def _apply_ids(
    store: MapStore, ids: I64, g: _Gathered | _PairGathered | _FewGathered, normals: bool, descriptors: bool
) -> None:
    """:func:`_apply` for the points ``ids`` (P,) in the order of g's rows."""
    write_point_updates(store, _updates(store, ids, g, normals, descriptors))


def _updates(
    store: MapStore,
    ids: I64,
    g: _Gathered | _PairGathered | _FewGathered,
    normals: bool,
    descriptors: bool,
    moved: tuple[I64, F64] | None = None,
) -> PointUpdates:
    """The points ``ids``' (P,, in the order of g's rows) new normals/depth ranges and descriptors, as updates for
    store.assign_points; moved: (ids (M,), xyz_w (M, 3)) positions replacing the stored ones of those points (ids
    among ``ids``, which must then be sorted)."""
    xyz = store.point_rows(ids, "xyz_w") if normals else np.zeros((ids.size, 3))  # read by the normals only
    if normals and moved is not None and moved[0].size:
        xyz = np.array(xyz, np.float64)  # a private copy (a store's point_rows need not copy)
        at = np.searchsorted(ids, moved[0])
        if not np.array_equal(ids[np.minimum(at, ids.size - 1)], moved[0]):
            raise ValueError("refreshed_points: a moved point is not among the refreshed ones")
        xyz[at] = moved[1]
    if g.desc.shape[1] % 8:
        raise ValueError(f"descriptors must have a multiple of 8 bytes, got {g.desc.shape[1]}")
    normal, has_normal, d_min, d_max, best = _refreshed(xyz, g, normals, descriptors)
    observed = g.n_observations > 0
    updates: PointUpdates = []
    if normals:
        with_normal = np.flatnonzero(observed & has_normal)
        with_ref = np.flatnonzero(observed & (g.ref_row >= 0))
        updates += [("normal_w", ids[with_normal], normal[with_normal])]
        updates += [("d_max_m", ids[with_ref], d_max[with_ref]), ("d_min_m", ids[with_ref], d_min[with_ref])]
    if descriptors:
        with_best = np.flatnonzero(best >= 0)
        updates += [("descriptor", ids[with_best], g.desc[best[with_best]])]
    return updates


class _FewGathered:
    """:class:`_Gathered`'s arrays for the descriptors alone (``normals=False``) of a few points, each point's
    observations walked in keyframe-id order (``sorted(point.observations)``): the same rows in the same order as
    _Gathered's sort and per-keyframe gathers, without their fixed cost of ~20 numpy calls (fusion refreshes the
    descriptors of a handful of surviving points ~26 times per keyframe)."""

    def __init__(self, store: MapStore, points: Sequence[MapPoint]) -> None:
        """Observers no longer in ``store`` are left out (as _Gathered does with the observers missing from its
        keyframes)."""
        P = len(points)
        rows: list[U8] = []
        ptr = [0]
        counts: list[int] = []
        descriptors: dict[int, U8 | None] = {}  # by observer: its keypoints' descriptors (None: not in the map)
        for point in points:
            obs = point.observations
            counts.append(len(obs))
            for k in sorted(obs):
                if k not in descriptors:
                    descriptors[k] = store.get_keyframe(k).features.descriptors if store.has_keyframe(k) else None
                d = descriptors[k]
                if d is not None:
                    rows.append(d[obs[k]])
            ptr.append(len(rows))
        E = len(rows)
        self.n_observations = np.array(counts, np.int64)
        self.ptr = np.array(ptr, np.int64)
        self.ref_row = np.full(P, -1, np.int64)
        self.center = np.zeros((E, 3))
        self.level = np.zeros(E, np.int64)
        self.desc = np.array(rows, np.uint8) if E else np.zeros((0, 32), np.uint8)
        self.scale_factor = np.ones(P)
        self.n_levels = np.ones(P, np.int64)


#: refresh_points of descriptors alone walks the observations point by point (:class:`_FewGathered`) up to this many
#: points; more go through _Gathered's sorted gathers (a tuning knob of the same result, not an ORB-SLAM constant)
FEW_POINTS = 48


def refresh_points(store: MapStore, point_ids: Iterable[int], normals: bool = True, descriptors: bool = True) -> None:
    """``update_normal_and_depth`` (when ``normals``) and ``compute_distinctive_descriptor`` (when
    ``descriptors``) for every listed point still in the map (duplicates and erased ids ignored), in one
    gather and one compiled pass."""
    write_point_updates(store, refreshed_points(store, point_ids, normals, descriptors))


#: what a refresh writes: (attribute, point ids (K,), values (K, ...)) for ``MapStore.assign_points``, in order
PointUpdates = list[tuple[str, I64, NDArray[Any]]]


def refreshed_points(
    store: MapStore,
    point_ids: Iterable[int],
    normals: bool = True,
    descriptors: bool = True,
    moved: tuple[I64, F64] | None = None,
    centers_w: Mapping[int, F64] | None = None,
) -> PointUpdates:
    """What :func:`refresh_points` would write, computed without writing (only reads the map: the read lock does).

    moved: (ids (M,), xyz_w (M, 3) m) positions to use instead of the stored ones for those points (listed points
    only); centers_w: keyframe id -> (3,) m camera centres to use instead of the keyframes' (their poses about to
    be written). With both, the updates are the ones ``refresh_points`` would write once those positions and poses
    are in the map, bit for bit (the same kernel on the same numbers)."""
    points = store.get_points(sorted(set(point_ids)))
    if not points:
        return []
    if descriptors and not normals and len(points) <= FEW_POINTS:
        return _updates(store, _ids_of(points), _FewGathered(store, points), False, True)
    flat = flat_observations(points)
    observers = np.unique(flat[1]).tolist()
    keyframes = {k: store.get_keyframe(k) for k in observers if store.has_keyframe(k)}
    g = _Gathered(points, keyframes, flat, len(keyframes) == len(observers), normals, descriptors, centers_w)
    return _updates(store, _ids_of(points), g, normals, descriptors, moved)


def write_point_updates(store: MapStore, updates: PointUpdates) -> None:
    """Write what :func:`refreshed_points` computed (store.assign_points of each update in order; the write lock)."""
    for name, ids, values in updates:
        store.assign_points(ids, name, values)


def update_normal_and_depth(store: MapStore, point: MapPoint, keyframes: Mapping[int, KeyFrame]) -> None:
    """Recompute ``normal_w`` (mean unit vector from the observing cameras to the point) and the distance
    range [d_min, d_max] in which ORB can detect it, from its reference keyframe's pyramid level:
    d_max = d_ref * scale^level, d_min = d_max / scale^(n_levels - 1) (ORB-SLAM MapPoint::UpdateNormalAndDepth).
    Observers missing from ``keyframes`` are ignored. ``point`` is a point of ``store``, which records the result.
    """
    _apply(store, [point], _Gathered([point], keyframes, flat_observations([point]), descriptors=False), True, False)


def compute_distinctive_descriptor(store: MapStore, point: MapPoint, keyframes: Mapping[int, KeyFrame]) -> None:
    """Choose as the point's descriptor the observation with the least median Hamming distance to all the
    others (ORB-SLAM MapPoint::ComputeDistinctiveDescriptors). Deterministic: ties go to the lowest keyframe id."""
    _apply(store, [point], _Gathered([point], keyframes, flat_observations([point]), normals=False), False, True)


def predict_level(
    d_max_m: NDArray[np.float64] | float,
    distance_m: NDArray[np.float64] | float,
    scale_factor: float,
    n_levels: int,
) -> NDArray[np.int64]:
    """Pyramid level at which a point at ``distance_m`` should be detected, given its d_max
    (ORB-SLAM MapPoint::PredictScale): ceil(log(d_max / d) / log(scale)), clipped to [0, n_levels - 1]."""
    ratio = np.asarray(d_max_m, np.float64) / np.maximum(np.asarray(distance_m, np.float64), 1e-12)
    level = np.ceil(np.log(np.maximum(ratio, 1e-12)) / np.log(scale_factor)).astype(np.int64)
    return np.asarray(np.clip(level, 0, n_levels - 1))


def create_depth_points(store: MapStore, kf: KeyFrame, min_points: int) -> list[int]:
    """New map points from the depths of a stereo/RGB-D keyframe in the map (ORB-SLAM2 Tracking::CreateNewKeyFrame).

    The keyframe's keypoints with a depth, nearest first: one without a map point gets a new point back-projected
    at its depth (Frame::UnprojectStereo), observed by ``kf``; each keypoint visited counts, matched or new, and the
    walk stops at the first far keypoint (depth >= th_depth_m) once more than ``min_points`` were counted: every
    close keypoint gets a point, far ones only until ``min_points``. Called under the write lock; returns the ids of
    the new points (descriptor, normal and depth range computed)."""
    feats = kf.features
    depth = feats.depth_m
    idx = np.flatnonzero(np.isfinite(depth) & (depth > 0))
    if idx.size == 0:
        return []
    order = idx[np.argsort(depth[idx], kind="stable")]
    pids = np.asarray(kf.point_ids, np.int64)
    has = np.zeros(pids.shape[0], np.bool_)
    has[pids >= 0] = store.has_points(pids[pids >= 0])
    create: list[int] = []
    for counted, i in enumerate(order.tolist(), start=1):
        if not has[i]:
            create.append(i)
        if depth[i] > feats.th_depth_m and counted > min_points:
            break
    if not create:
        return []
    sel = np.array(create, np.int64)
    xyz = feats.unproject_stereo(sel, invert_T(kf.T_c_w), kf.camera.K)
    created = [store.new_point_id() for _ in create]
    # the points and their one observation each written at once (the keypoints in ``create`` are distinct)
    desc = feats.descriptors
    add_points(
        store,
        [MapPoint(pid, xyz[m], desc[i], kf.id, kf.id) for m, (pid, i) in enumerate(zip(created, create, strict=True))],
    )
    add_observations(store, np.array(created, np.int64), kf.id, sel)
    refresh_points(store, created)
    return created


def add_points(store: MapStore, points: Sequence[MapPoint]) -> None:
    """``store.add_point`` of each point in order: at once through the store's ``add_points`` where it has one
    (InMemoryMapStore; the MapStore protocol asks for the one-point form only), else one at a time."""
    batch = getattr(store, "add_points", None)
    if batch is not None:
        batch(points)
        return
    for point in points:
        store.add_point(point)


def add_observations(store: MapStore, point_ids: I64, keyframe_id: int, feature_indices: I64) -> None:
    """``store.add_observation(point_ids[q], keyframe_id, feature_indices[q])`` for q in order (P,): at once through
    the store's ``add_observations`` where it has one (InMemoryMapStore), else one at a time."""
    batch = getattr(store, "add_observations", None)
    if batch is not None:
        batch(point_ids, keyframe_id, feature_indices)
        return
    for pid, feat in zip(np.asarray(point_ids).tolist(), np.asarray(feature_indices).tolist(), strict=True):
        store.add_observation(pid, keyframe_id, feat)


def orbslam_observation_counts(store: MapStore, point_ids: Iterable[int]) -> I64:
    """(P,) ORB-SLAM's MapPoint::Observations() of each point (all in the map): its observations, a stereo/RGB-D one
    (the keypoint has a right coordinate) counting twice (MapPoint::AddObservation: nObs += 2 when mvuRight[idx] >= 0).

    One array read of the store's ``n_observations_orbslam`` counter; a third-party store without that counter
    (KeyError) is counted point by point from the observations."""
    ids = np.asarray(point_ids if isinstance(point_ids, np.ndarray) else list(point_ids), np.int64)
    if not ids.size:
        return np.zeros(0, np.int64)
    try:
        return np.asarray(store.point_rows(ids, "n_observations_orbslam"), np.int64)
    except KeyError:
        pass
    out = []
    for pid in ids.tolist():
        n = 0
        for kf_id, idx in store.get_point(pid).observations.items():
            n += observation_weight(store.get_keyframe(kf_id).features, idx)
        out.append(n)
    return np.array(out, np.int64)
