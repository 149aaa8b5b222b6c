"""Local keyframe culling (ORB-SLAM sec. VI-E, LocalMapping::KeyFrameCulling) without a Python loop per
observation: the observations of every point the candidates see are gathered once into flat arrays, and a
numba pass (GIL released) counts, for one candidate, the points seen at the same or a finer scale by at least
``min_observers`` other keyframes. Culling a candidate only marks its observation rows dead, so the later
candidates see the map exactly as the per-point loop of ORB-SLAM would.
"""

from __future__ import annotations

from collections.abc import Sequence

import numba
import numpy as np
from numpy.typing import NDArray

from slamkit.interfaces import MapStore
from slamkit.pipeline.map_points import flat_observations, unique_point_ids

I64 = NDArray[np.int64]


@numba.njit(cache=True, nogil=True)
def _count_redundant(
    rows_of: I64, level_of: I64, ptr: I64, obs_kf: I64, obs_level: I64, alive: NDArray[np.bool_], kf_id: int, m: int
) -> int:  # pragma: no cover - compiled
    """Points q = rows_of[i] (seen by ``kf_id`` at pyramid level level_of[i]) that have more than m live
    observations and at least m of them, by other keyframes, at level <= level_of[i] + 1."""
    redundant = 0
    for i in range(rows_of.shape[0]):
        q = rows_of[i]
        n_live = 0
        n_obs = 0
        for e in range(ptr[q], ptr[q + 1]):
            if not alive[e]:
                continue
            n_live += 1
            if obs_kf[e] != kf_id and obs_level[e] <= level_of[i] + 1:
                n_obs += 1
        if n_live > m and n_obs >= m:
            redundant += 1
    return redundant


class ObservationTable:
    """Every observation of the points seen by some keyframes, grouped by point (CSR: rows ptr[q]:ptr[q+1]).

    point_ids: (P,) sorted ids; obs_kf / obs_level: (E,) observing keyframe and the feature's pyramid level;
    alive: (E,) False once the observing keyframe is culled.
    """

    def __init__(self, store: MapStore, kf_ids: Sequence[int]) -> None:
        self.store = store
        ids = unique_point_ids([store.get_keyframe(k).point_ids for k in kf_ids])
        self.point_ids = ids[store.has_points(ids)].astype(np.int64)
        counts, self.obs_kf, feat = flat_observations(store.get_points(self.point_ids.tolist()))
        self.ptr = np.zeros(counts.size + 1, np.int64)
        np.cumsum(counts, out=self.ptr[1:])
        kf_of = self.obs_kf
        self.obs_level = np.zeros(len(kf_of), np.int64)
        order = np.argsort(self.obs_kf, kind="stable")
        uniq, starts = np.unique(self.obs_kf[order], return_index=True)
        bounds = np.append(starts, len(kf_of))
        for i, k in enumerate(uniq.tolist()):
            rows = order[bounds[i] : bounds[i + 1]]
            self.obs_level[rows] = store.get_keyframe(k).features.level[feat[rows]]
        self.alive = np.ones(len(kf_of), np.bool_)

    def redundancy(self, kf_id: int, min_observers: int) -> tuple[int, int]:
        """(points of ``kf_id`` still in the map, those seen by >= min_observers other keyframes at the same or
        a finer scale, among points with more than min_observers observations) (ORB-SLAM thObs = 3).

        A stereo/RGB-D keyframe (bf > 0) counts only its points observed with a depth up to its close threshold
        (ORB-SLAM2 KeyFrameCulling: ``if(!mbMonocular)`` skips a point whose keypoint depth is > mThDepth or < 0).
        ORB-SLAM2's first test ``Observations() > thObs`` counts a stereo observation twice; it never decides here:
        a point with nObs >= thObs other observers has more than thObs observers in either count."""
        kf = self.store.get_keyframe(kf_id)
        has_point = kf.point_ids >= 0
        if kf.features.bf > 0.0:
            depth = kf.features.depth_m
            has_point &= np.isfinite(depth) & (depth >= 0.0) & (depth <= kf.features.th_depth_m)
        feats = np.flatnonzero(has_point)
        pids = kf.point_ids[feats]
        if pids.size == 0 or self.point_ids.size == 0:
            return 0, 0
        q = np.minimum(np.searchsorted(self.point_ids, pids), self.point_ids.size - 1)
        # every point a live keyframe sees is in the table (culling only erases points left unobserved)
        known = self.point_ids[q] == pids
        rows = q[known]
        levels = np.asarray(kf.features.level[feats[known]], np.int64)
        if rows.size == 0:
            return 0, 0
        redundant = _count_redundant(
            rows.astype(np.int64), levels, self.ptr, self.obs_kf, self.obs_level, self.alive, kf_id, min_observers
        )
        return int(rows.size), int(redundant)

    def cull(self, kf_id: int) -> None:
        """Forget the observations of a keyframe erased from the map."""
        self.alive &= self.obs_kf != kf_id
