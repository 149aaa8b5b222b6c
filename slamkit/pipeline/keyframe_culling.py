"""Local keyframe culling (ORB-SLAM sec. VI-E, LocalMapping::KeyFrameCulling) without a Python loop per
observation: the observations of every point the candidates see are gathered once into flat arrays, and a
numba pass (GIL released) counts, for every candidate at once, the points seen at the same or a finer scale by at
least ``min_observers`` other keyframes. Culling a candidate only marks its observation rows dead, so the later
candidates see the map exactly as the per-point loop of ORB-SLAM would (their counts are taken again after a cull).
"""

from __future__ import annotations

from collections.abc import Sequence

import numba
import numpy as np
from numpy.typing import NDArray

from slamkit.interfaces import MapStore
from slamkit.pipeline.map_points import gather_observations, unique_point_ids

I64 = NDArray[np.int64]
B = NDArray[np.bool_]


@numba.njit(cache=True, nogil=True)
def _count_redundant(
    cand_ptr: I64,
    cand_kf: I64,
    pids: I64,
    levels: I64,
    eligible: B,
    rows: I64,
    point_ids: I64,
    ptr: I64,
    obs_kf: I64,
    obs_level: I64,
    alive: B,
    point_dead: B,
    m: int,
    first: int,
) -> tuple[I64, I64]:  # pragma: no cover - compiled
    """For each candidate c (C,): its features f in cand_ptr[c]:cand_ptr[c + 1] of the flat arrays pids / levels /
    eligible / rows (F,) (point id or -1, pyramid level, whether the feature counts, row of pids[f] in the sorted
    ``point_ids`` (P,): any row >= P, or of another id, when it is not there; :func:`table_rows`) -> (n_points (C,):
    eligible features whose point is in the table, redundant (C,): those of them whose point has more than m live
    observations and at least m of them, by keyframes other than cand_kf[c], at level <= the feature's level + 1), for
    the candidates from ``first`` on (0 before). A point of row q with point_dead[q] was erased from the map after the
    features were gathered: it counts as no point."""
    C = cand_kf.shape[0]
    P = point_ids.shape[0]
    n_points = np.zeros(C, np.int64)
    redundant = np.zeros(C, np.int64)
    for c in range(first, C):
        kf_id = cand_kf[c]
        for f in range(cand_ptr[c], cand_ptr[c + 1]):
            pid = pids[f]
            if pid < 0 or not eligible[f]:
                continue
            q = rows[f]
            if q >= P or point_ids[q] != pid or point_dead[q]:
                continue
            n_points[c] += 1
            limit = levels[f] + 1
            n_live = 0
            n_obs = 0
            for e in range(ptr[q], ptr[q + 1]):
                if not alive[e]:
                    continue
                n_live += 1
                if obs_kf[e] != kf_id and obs_level[e] <= limit:
                    n_obs += 1
            if n_live > m and n_obs >= m:
                redundant[c] += 1
    return n_points, redundant


def table_rows(point_ids: I64, pids: I64) -> I64:
    """The row of each id of ``pids`` (F,) in ``point_ids`` (P,) (sorted, distinct, non-negative), or P where it is not
    there (-1 included) -> (F,) int64: a lookup table over point_ids' id range, one gather (a binary search per
    feature over tens of thousands of features was ~1.5 ms per keyframe on fr1_xyz). :func:`_count_redundant` takes
    a feature as pointing at a point of the table exactly when its row is < P and holds its id, as it did with the
    insertion rows of ``np.searchsorted``."""
    P = point_ids.size
    rows = np.full(pids.size, P, np.int64)
    if P == 0 or pids.size == 0:
        return rows
    lo, hi = int(point_ids[0]), int(point_ids[-1])
    lut = np.full(hi - lo + 1, P, np.int64)
    lut[point_ids - lo] = np.arange(P, dtype=np.int64)
    inside = np.flatnonzero((pids >= lo) & (pids <= hi))
    rows[inside] = lut[pids[inside] - lo]
    return rows


class ObservationTable:
    """Every observation of the points seen by some keyframes, grouped by point (CSR: rows ptr[q]:ptr[q+1]).

    point_ids: (P,) sorted ids; obs_kf / obs_level: (E,) observing keyframe and the feature's pyramid level;
    alive: (E,) False once the observing keyframe is culled; point_dead: (P,) True once the point is erased.
    """

    def __init__(self, store: MapStore, kf_ids: Sequence[int]) -> None:
        self.store = store
        ids = unique_point_ids([store.get_keyframe(k).point_ids for k in kf_ids])
        self.point_ids = ids[store.has_points(ids)].astype(np.int64)
        counts, self.obs_kf, feat = gather_observations(store, self.point_ids)
        self.ptr = np.zeros(counts.size + 1, np.int64)
        np.cumsum(counts, out=self.ptr[1:])
        self.obs_level = np.zeros(self.obs_kf.size, np.int64)
        if self.obs_kf.size:
            # each observation's level from its keyframe's level array: the observers' arrays laid end to end, an
            # observation at (its keyframe's offset + its feature index); the observers found by a mark per id
            present = np.zeros(int(self.obs_kf.max()) + 1, bool)
            present[self.obs_kf] = True
            observers = np.flatnonzero(present)
            level_arrays = [store.get_keyframe(k).features.level for k in observers.tolist()]
            offsets = np.zeros(observers.size + 1, np.int64)
            np.cumsum([a.size for a in level_arrays], out=offsets[1:])
            slot = np.zeros(present.size, np.int64)
            slot[observers] = offsets[:-1]
            self.obs_level = np.concatenate(level_arrays).astype(np.int64)[slot[self.obs_kf] + feat]
        self.alive = np.ones(self.obs_kf.size, np.bool_)
        self.point_dead = np.zeros(self.point_ids.size, np.bool_)
        self._candidates: tuple[tuple[int, ...], I64, I64, I64, I64, B, I64] | None = None

    def redundancies(self, kf_ids: Sequence[int], min_observers: int, first: int = 0) -> tuple[I64, I64]:
        """:meth:`redundancy` of each keyframe of ``kf_ids`` (K,) (each in the map when first asked) in one compiled
        pass over the map as it is now, for kf_ids[first:] (zeros before) -> (n_points (K,), redundant (K,)).

        The keyframes' point ids, levels and depth filter are gathered on the first call for a list and kept for the
        next calls with the same list (keyframe culling asks again after each cull, for the keyframes after it):
        culling changes them only by erasing points, which :meth:`cull` records."""
        key = tuple(kf_ids)
        if self._candidates is None or self._candidates[0] != key:
            self._candidates = (key, *self._gather_candidates(key))
        _, cand_ptr, cand_kf, pids, levels, eligible, rows = self._candidates
        return _count_redundant(
            cand_ptr,
            cand_kf,
            pids,
            levels,
            eligible,
            rows,
            self.point_ids,
            self.ptr,
            self.obs_kf,
            self.obs_level,
            self.alive,
            self.point_dead,
            int(min_observers),
            int(first),
        )

    def _gather_candidates(self, kf_ids: tuple[int, ...]) -> tuple[I64, I64, I64, I64, B, I64]:
        """The keyframes' features laid end to end: (ptr (K + 1,), keyframe ids (K,), then per feature (F,): point id
        or -1, level, whether it counts (stereo/RGB-D: a depth within the close threshold), its point's table row)."""
        kfs = [self.store.get_keyframe(k) for k in kf_ids]
        cand_ptr = np.zeros(len(kfs) + 1, np.int64)
        np.cumsum([kf.point_ids.size for kf in kfs], out=cand_ptr[1:])
        if not kfs:
            empty = np.zeros(0, np.int64)
            return cand_ptr, empty, empty, empty, np.zeros(0, np.bool_), empty
        pids = np.concatenate([kf.point_ids for kf in kfs]).astype(np.int64, copy=False)
        levels = np.concatenate([kf.features.level for kf in kfs]).astype(np.int64, copy=False)
        eligible = np.ones(pids.size, np.bool_)
        for c, kf in enumerate(kfs):
            if kf.features.bf > 0.0:
                depth = kf.features.depth_m
                eligible[cand_ptr[c] : cand_ptr[c + 1]] = (
                    np.isfinite(depth) & (depth >= 0.0) & (depth <= kf.features.th_depth_m)
                )
        return cand_ptr, np.array(kf_ids, np.int64), pids, levels, eligible, table_rows(self.point_ids, pids)

    def redundancy(self, kf_id: int, min_observers: int) -> tuple[int, int]:
        """(points of ``kf_id`` still in the map, those seen by >= min_observers other keyframes at the same or
        a finer scale, among points with more than min_observers observations) (ORB-SLAM thObs = 3).

        A stereo/RGB-D keyframe (bf > 0) counts only its points observed with a depth up to its close threshold
        (ORB-SLAM2 KeyFrameCulling: ``if(!mbMonocular)`` skips a point whose keypoint depth is > mThDepth or < 0).
        ORB-SLAM2's first test ``Observations() > thObs`` counts a stereo observation twice; it never decides here:
        a point with nObs >= thObs other observers has more than thObs observers in either count. Every point a live
        keyframe sees is in the table (culling only erases points left unobserved)."""
        n_points, redundant = self.redundancies([kf_id], min_observers)
        return int(n_points[0]), int(redundant[0])

    def cull(self, kf_id: int, erased_points: I64 | None = None) -> None:
        """Forget the observations of a keyframe erased from the map, and the points ``erased_points`` erased with it
        (those other keyframes observed: the keyframes' point ids gathered by :meth:`redundancies` still name them)."""
        self.alive &= self.obs_kf != kf_id
        if erased_points is not None and erased_points.size and self.point_ids.size:
            q = np.minimum(np.searchsorted(self.point_ids, erased_points), self.point_ids.size - 1)
            self.point_dead[q[self.point_ids[q] == erased_points]] = True
