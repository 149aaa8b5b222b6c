"""Fusing map points into a keyframe (ORB-SLAM ORBmatcher::Fuse and MapPoint::Replace): project points into
the keyframe; a match either adds an observation or merges two points that are the same 3D point."""

from __future__ import annotations

from collections.abc import Callable

import numba
import numpy as np
from numpy.typing import NDArray

from slamkit.interfaces import MapStore
from slamkit.map.entities import KeyFrame, MapPoint
from slamkit.pipeline.frame import ImageBounds, keyframe_cameras, keyframe_view
from slamkit.pipeline.map_points import refresh_points
from slamkit.pipeline.projection import (
    frustum_test,
    fuse_reprojection_gate,
    match_projected,
    predicted_u_right,
)

I64 = NDArray[np.int64]


@numba.njit(cache=True, nogil=True)
def absent_from(ids: I64, own: I64) -> NDArray[np.bool_]:  # pragma: no cover - compiled
    """(Q,) bool: ids[q] is none of the point ids ``own`` (N,) (-1: no point), i.e. ``~np.isin(ids, own[own >= 0])``
    in one compiled pass over a lookup table of own's id range (fusion asks it once per fused keyframe pair)."""
    lo = np.iinfo(np.int64).max
    hi = -1
    for v in own:
        if v >= 0:
            lo = min(lo, v)
            hi = max(hi, v)
    out = np.ones(ids.shape[0], np.bool_)
    if hi < 0:
        return out
    mark = np.zeros(hi - lo + 1, np.bool_)
    for v in own:
        if v >= 0:
            mark[v - lo] = True
    for q in range(ids.shape[0]):
        v = ids[q]
        if lo <= v <= hi and mark[v - lo]:
            out[q] = False
    return out


class KeyFramePoints:
    """The points one keyframe observes as fusion candidates, with the rows fusion's frustum test reads (position,
    normal, depth range), kept across the passes that fuse them into one neighbour after another (local mapping's
    SearchInNeighbors: ~20-25 passes per keyframe). :meth:`update` re-reads the keyframe's point ids and which of
    them are in the map, and gathers the rows only at the keypoints whose point changed since the last pass (a merge
    puts the surviving point there): the same ids, in the same (keypoint) order, with the same rows as
    ``store.point_rows`` of ``kf.point_ids[kf.point_ids >= 0]`` in the map, provided no point's position, normal or
    depth range moves between the passes (fusion refreshes descriptors only; local BA runs after it)."""

    def __init__(self, kf: KeyFrame) -> None:
        """kf: the keyframe whose points are fused (its ``point_ids`` (N,) read at each update)."""
        self.kf = kf
        n = kf.point_ids.shape[0]
        self._at = np.full(n, -1, np.int64)  # the point whose rows each keypoint's slot holds (-1: none)
        self._xyz = np.zeros((n, 3))
        self._normal = np.zeros((n, 3))
        self._d_min = np.zeros(n)
        self._d_max = np.zeros(n)
        self.ids = np.zeros(0, np.int64)
        self.xyz_w = np.zeros((0, 3))
        self.normal_w = np.zeros((0, 3))
        self.d_min_m = np.zeros(0)
        self.d_max_m = np.zeros(0)

    def update(self, store: MapStore) -> KeyFramePoints:
        """Read the keyframe's points now: ids (K,) in keypoint order, xyz_w (K, 3) m, normal_w (K, 3), d_min_m and
        d_max_m (K,) m (world frame). Returns self."""
        pids = np.asarray(self.kf.point_ids, np.int64)
        slots = np.flatnonzero(pids >= 0)
        slots = slots[store.has_points(pids[slots])]
        ids = pids[slots]
        stale = slots[self._at[slots] != ids]
        if stale.size:
            fresh = pids[stale]
            self._xyz[stale] = store.point_rows(fresh, "xyz_w")
            self._normal[stale] = store.point_rows(fresh, "normal_w")
            self._d_min[stale] = store.point_rows(fresh, "d_min_m")
            self._d_max[stale] = store.point_rows(fresh, "d_max_m")
            self._at[stale] = fresh
        self.ids = ids
        self.xyz_w = self._xyz[slots]
        self.normal_w = self._normal[slots]
        self.d_min_m = self._d_min[slots]
        self.d_max_m = self._d_max[slots]
        return self


def replace_point(store: MapStore, old: MapPoint, new: MapPoint, refresh: bool = True) -> None:
    """Move every observation of ``old`` to ``new`` (where ``new`` is not already observed) and erase old.

    ``refresh=False`` leaves ``new``'s descriptor to the caller (fusion recomputes its survivors in one batch,
    after its matches, which read the descriptors before any replacement anyway)."""
    store.replace_point(old.id, new.id)
    if refresh:
        refresh_points(store, [new.id], normals=False)


def fuse_points(
    store: MapStore,
    kf: KeyFrame,
    point_ids: list[int] | I64 | KeyFramePoints,
    radius_px: float,
    incoming_wins: bool = False,
    *,
    max_distance: int,
    chi2_gate: float,
    chi2_gate_stereo: float | None = None,
    refresh_survivors: bool = True,
) -> int:
    """Project ``point_ids`` into ``kf`` and fuse each match (radius_px scaled by the predicted level).

    When the matched feature already has another point, the one with more observations survives (local
    mapping, ORB-SLAM Fuse), or always the incoming one with ``incoming_wins`` (loop fusion, ORB-SLAM
    SearchAndFuse). max_distance: Hamming threshold, bits (pipeline.matcher.th_low); chi2_gate: reprojection
    gate over the level's sigma^2 (pipeline.chi2.fuse_mono). Returns the number of fused matches.

    chi2_gate_stereo: with a stereo/RGB-D keyframe (bf > 0), ORB-SLAM2 Fuse(pKF, vpMapPoints)'s gate on every
    candidate in the window before the descriptor comparison: 3 dof with the right coordinate (u_R = u - bf / z)
    against this threshold (pipeline.chi2.stereo_rounded, 7.8), 2 dof against ``chi2_gate`` for a candidate without
    one. None, or a monocular keyframe: the 2-dof gate on the best match only (slamkit's monocular fusion).

    point_ids: the ids, or a :class:`KeyFramePoints` updated for this call (its ids with the rows it holds).

    refresh_survivors=False (a one-camera keyframe): the merges' surviving points keep their descriptors; the caller
    refreshes the descriptors of every point ``kf`` observes before anything reads them (local mapping's
    SearchInNeighbors, right after its last fusion), which covers the survivors: each holds a keypoint of ``kf``.
    """
    if not kf.features.two_cameras:
        return _fuse_view(
            store,
            kf,
            kf,
            None,
            point_ids,
            radius_px,
            incoming_wins,
            max_distance,
            chi2_gate,
            chi2_gate_stereo,
            refresh_survivors,
        )
    # a two-camera keyframe (ORB-SLAM3 SearchInNeighbors: Fuse(pKF, points) then Fuse(pKF, points, bRight = true)):
    # each camera's keypoints through that camera
    cam = kf.features.camera_index()
    return sum(
        _fuse_view(
            store,
            kf,
            keyframe_view(kf, c),
            cam != c,
            point_ids,
            radius_px,
            incoming_wins,
            max_distance,
            chi2_gate,
            chi2_gate_stereo,
            True,  # the second camera's matching reads the first's survivors
        )
        for c in keyframe_cameras(kf)
    )


def _fuse_view(
    store: MapStore,
    kf: KeyFrame,
    view: KeyFrame,
    taken: NDArray[np.bool_] | None,
    point_ids: list[int] | I64 | KeyFramePoints,
    radius_px: float,
    incoming_wins: bool,
    max_distance: int,
    chi2_gate: float,
    chi2_gate_stereo: float | None,
    refresh_survivors: bool = True,
) -> int:
    """fuse_points into one camera of ``kf``: ``view`` gives the pose and camera model (``kf`` itself for a one-camera
    keyframe, :func:`keyframe_view`), ``taken`` (N,) the keypoints of the other camera (None: none)."""
    kf_id = kf.id
    held = point_ids if isinstance(point_ids, KeyFramePoints) else None
    if isinstance(point_ids, KeyFramePoints):
        ids = point_ids.ids
    else:
        ids = np.asarray(point_ids if isinstance(point_ids, np.ndarray) else list(point_ids), np.int64).reshape(-1)
        ids = ids[store.has_points(ids)]
    # leave out the points kf observes already: an observation is recorded in both directions (MapStore.add_observation:
    # point.observations[kf] = f and kf.point_ids[f] = point), so they are the candidates among kf's point_ids
    keep = absent_from(ids, kf.point_ids)
    if held is not None and taken is not None:  # a two-camera keyframe's second view: the first's merges erased some
        keep &= store.has_points(ids)
    ids = ids[keep]
    if not ids.size or len(kf.features) == 0:
        return 0
    feats = kf.features
    bounds = ImageBounds.of(view.camera)
    if held is not None:
        xyz, normal, d_min, d_max = held.xyz_w[keep], held.normal_w[keep], held.d_min_m[keep], held.d_max_m[keep]
    else:
        xyz, normal = store.point_rows(ids, "xyz_w"), store.point_rows(ids, "normal_w")
        d_min, d_max = store.point_rows(ids, "d_min_m"), store.point_rows(ids, "d_max_m")
    test = frustum_test(
        view.T_c_w,
        view.camera,
        bounds,
        xyz,
        normal,
        d_min,
        d_max,
        0.5,
        feats.scale_factor,
        feats.n_levels,
    )
    q = np.flatnonzero(test.visible)
    if q.size == 0:
        return 0
    level = test.predicted_level[q]
    radius = radius_px * np.power(feats.scale_factor, level)
    in_window_gate = chi2_gate_stereo is not None and feats.bf > 0.0
    right_gate = None
    if in_window_gate:
        assert chi2_gate_stereo is not None
        u_right = predicted_u_right(test.uv_px[q], test.z_m[q], feats.bf)
        right_gate = fuse_reprojection_gate(feats, u_right, chi2_gate, chi2_gate_stereo)
    m = match_projected(
        feats,
        np.zeros(len(feats), bool) if taken is None else taken,
        bounds,
        test.uv_px[q],
        store.point_rows(ids[q], "descriptor"),
        radius,
        level - 1,
        level,
        max_distance,
        None,
        None,
        None,
        right_gate=right_gate,
        reuse_grid=taken is None,  # a one-camera keyframe's features: the same grid for every point set fused into it
    )
    if in_window_gate:
        gated = np.ones(len(m), bool)  # every candidate was gated in the window
    else:
        sigma2 = feats.level_sigma2()
        uv_pred = test.uv_px[q[m.query]]
        err2 = np.sum((uv_pred - feats.uv_undist_px[m.feature]) ** 2, axis=1)
        gated = err2 <= chi2_gate * sigma2[m.feature]
    rows, features = m.query[gated], m.feature[gated]
    batch = getattr(store, "add_observations", None)
    if taken is None and batch is not None:
        done = _fuse_one_camera(store, kf, ids[q[rows]], features, incoming_wins, batch, refresh_survivors)
        if done is not None:
            return done
    fused = 0
    survivors: list[int] = []
    for row, feat in zip(rows.tolist(), features.tolist(), strict=True):
        pid = int(ids[q[row]])
        if not store.has_point(pid):
            continue
        point = store.get_point(pid)
        if kf_id in point.observations:
            continue
        existing = int(kf.point_ids[feat])
        if existing < 0 and taken is not None and feats.stereo_match is not None and feats.stereo_match[feat] >= 0:
            existing = int(kf.point_ids[int(feats.stereo_match[feat])])  # the stereo partner's point stands for both
        if existing >= 0 and store.has_point(existing):
            if existing == point.id:
                continue
            other = store.get_point(existing)
            if not incoming_wins and len(other.observations) > len(point.observations):
                replace_point(store, point, other, refresh=False)
                survivors.append(other.id)
            else:
                replace_point(store, other, point, refresh=False)
                survivors.append(point.id)
        else:
            store.add_observation(point.id, kf_id, feat)
        fused += 1
    if refresh_survivors:
        refresh_points(store, survivors, normals=False)  # ORB-SLAM Replace: the survivor's descriptor
    return fused


def _fuse_one_camera(
    store: MapStore,
    kf: KeyFrame,
    pids: I64,
    features: I64,
    incoming_wins: bool,
    add_observations: Callable[[I64, int, I64], None],
    refresh_survivors: bool = True,
) -> int | None:
    """_fuse_view's matches for a one-camera keyframe, point pids[i] (M,) at keypoint features[i] (M,) of ``kf``
    (points kf does not observe, distinct keypoints): the same map as the loop over the matches in their order, with
    the keypoints that have no point in one batch (``add_observations``, the in-memory store's). Returns the number
    fused, or None (nothing done) unless the points are distinct and in the map and the points at the keypoints are
    distinct: then the loop decides.

    Each match then changes only its own point, the point at its keypoint and that keypoint of kf (a point's
    observations move only when it is replaced by, or replaces, the point at its keypoint), so the batch of new
    observations commutes with the replacements, which still run one at a time in the matches' order."""
    if not pids.size:
        return 0
    listed = pids.tolist()
    if len(set(listed)) != len(listed) or not store.has_points(pids).all():  # (a set: no sort of a few ids)
        return None
    kf_id = kf.id
    if any(kf_id in point.observations for point in store.get_points(listed)):
        return None  # kf observes one at another keypoint (kf's point_ids should have ruled it out): the loop's rule
    existing = kf.point_ids[features]
    has_other = existing >= 0
    if has_other.any():
        has_other[has_other] = store.has_points(existing[has_other])
        others = existing[has_other].tolist()
        if len(set(others)) != len(others):
            return None
    free = ~has_other
    fused = int(free.sum())
    if fused:
        add_observations(pids[free], kf_id, features[free])
    survivors: list[int] = []
    for pid, other_id in zip(pids[has_other].tolist(), existing[has_other].tolist(), strict=True):
        if other_id == pid:
            continue
        point, other = store.get_point(pid), store.get_point(other_id)
        if not incoming_wins and len(other.observations) > len(point.observations):
            replace_point(store, point, other, refresh=False)
            survivors.append(other_id)
        else:
            replace_point(store, other, point, refresh=False)
            survivors.append(pid)
        fused += 1
    if refresh_survivors:
        refresh_points(store, survivors, normals=False)  # ORB-SLAM Replace: the survivor's descriptor
    return fused
