"""ORB-SLAM sec. V-D: tracking the local map (Tracking::TrackLocalMap: UpdateLocalKeyFrames, SearchLocalPoints,
PoseOptimization). The caller holds the map's read lock."""

from __future__ import annotations

from collections import Counter
from itertools import chain
from operator import attrgetter

import numpy as np
from numpy.typing import NDArray

from slamkit.interfaces import MapStore
from slamkit.pipeline.config import TrackingConfig
from slamkit.pipeline.frame import CameraView, Frame, camera_views
from slamkit.pipeline.projection import (
    FrustumTest,
    frustum_test,
    match_projected,
    predicted_u_right,
    project_points,
    radius_by_viewing_cos,
    right_u_gate,
)
from slamkit.pipeline.tracking.frame_pose import PoseRefiner

I64 = NDArray[np.int64]

_OBSERVATIONS = attrgetter("observations")


def local_keyframes(frame: Frame, store: MapStore, cfg: TrackingConfig) -> tuple[list[int], int | None]:
    """V-D as ORB-SLAM2's Tracking::UpdateLocalKeyFrames: K1 = every keyframe sharing points with the frame (most
    shared first, uncapped); then, for each K1 keyframe while the set holds at most
    ``local_map_covisible_keyframes`` keyframes, K2 adds three at most: the first of its
    ``local_map_neighbors_per_keyframe`` best covisible neighbours not in the set yet, its first spanning-tree child
    (lowest id) not in the set yet, and its parent if not in the set yet.

    Returns (local keyframe ids, K_ref: the K1 keyframe sharing the most points, None when the frame matched no
    point). ORB-SLAM2's code also leaves the K1 loop after the first parent it adds (a ``break`` inside the parent
    branch, kept in ORB-SLAM3); slamkit goes on with the next K1 keyframe, as the comment of that loop says
    (docs/pipeline.md)."""
    # the observing keyframe ids are walked by C iterators (map / chain / Counter), not a Python loop per point
    matched = map(store.get_point, frame.point_ids[frame.point_ids >= 0].tolist())
    counts = Counter(chain.from_iterable(map(_OBSERVATIONS, matched)))
    k1 = sorted((k for k in counts if store.has_keyframe(k)), key=lambda k: (-counts[k], k))
    if not k1:
        return [], None
    local = list(k1)
    seen = set(local)
    tree = store.spanning_tree

    def add_first(options: list[int]) -> None:
        for other in options:
            if other not in seen and store.has_keyframe(other):
                local.append(other)
                seen.add(other)
                return

    for kf_id in k1:
        if len(local) > cfg.local_map_covisible_keyframes:
            break
        add_first(store.covisibility.best_neighbors(kf_id, cfg.local_map_neighbors_per_keyframe))
        add_first(tree.children(kf_id))
        parent = tree.parent(kf_id)
        add_first([] if parent is None else [parent])
    return local, k1[0]


def points_seen_except(ids: I64, excluded: I64) -> I64:
    """The distinct point ids >= 0 of ``ids`` (the local keyframes' slots, -1 = none) that are not in ``excluded``,
    ascending: ``np.setdiff1d(np.unique(ids[ids >= 0]), excluded)``, by marking a table over the id range instead
    of sorting (tens of thousands of slots per frame: a sort was ~10x slower)."""
    seen = ids[ids >= 0]
    if seen.size == 0:
        return np.zeros(0, np.int64)
    marked = np.zeros(int(seen.max()) + 1, np.bool_)
    marked[seen] = True
    excluded = excluded[(excluded >= 0) & (excluded < marked.size)]
    marked[excluded] = False
    return np.flatnonzero(marked).astype(np.int64, copy=False)


def track_local_map(
    frame: Frame, store: MapStore, cfg: TrackingConfig, refiner: PoseRefiner, wide_search: bool
) -> tuple[int, int | None]:
    """V-D: project the local map's points with the five filters, match, optimize the pose again.

    wide_search: the frame follows a relocalization closely (radius ``local_map_search_radius_relocalized_px``).
    Returns (inliers: matched points observed by some keyframe, K_ref or None when the frame matched no point)."""
    frame.point_ids[~store.has_points(frame.point_ids)] = -1
    local_kfs, reference_kf_id = local_keyframes(frame, store, cfg)
    matched = np.unique(frame.point_ids[frame.point_ids >= 0])
    store.increase_visible(matched)
    if local_kfs:
        ids = np.concatenate([store.get_keyframe(k).point_ids for k in local_kfs])
        candidates = points_seen_except(ids, matched)
        if candidates.size:
            search_local_points(frame, candidates.astype(np.int64), store, cfg, wide_search)
    assert frame.T_c_w is not None
    refiner.optimize(frame, frame.T_c_w)
    found = frame.point_ids[(frame.point_ids >= 0) & ~frame.outlier]
    if found.size == 0:
        return 0, reference_kf_id
    store.increase_found(found)
    return int(np.count_nonzero(store.point_rows(found, "n_observations") > 0)), reference_kf_id


def search_local_points(frame: Frame, candidates: I64, store: MapStore, cfg: TrackingConfig, wide_search: bool) -> None:
    """ORB-SLAM SearchLocalPoints: the frustum test of every candidate (sorted point ids not matched yet), then the
    search around the projections of the visible ones. Attributes are read only as far as a point gets: the
    position of all, the viewing data of those projecting into the image, the descriptor of the visible ones.

    A two-camera frame (ORB-SLAM3 Frame::isInFrustum with isInFrustumChecks for mpCamera and mpCamera2): a point is
    visible (its visible counter raised once) when it passes the test in either camera, and is searched among the
    keypoints of each camera it passes in (SearchByProjection's mbTrackInView / mbTrackInViewR), so it may be matched
    in both."""
    feats = frame.features
    assert frame.T_c_w is not None
    xyz = store.point_rows(candidates, "xyz_w")
    views = camera_views(frame, frame.T_c_w)
    tests: list[tuple[CameraView, I64, FrustumTest]] = []
    for view in views:
        uv, _, in_image = project_points(view.T_c_w, xyz, view.camera)
        in_image &= view.bounds.contains(np.where(np.isfinite(uv), uv, -1e9))
        s = np.flatnonzero(in_image)
        if s.size == 0:
            continue
        near = candidates[s]
        test = frustum_test(
            view.T_c_w,
            view.camera,
            view.bounds,
            xyz[s],
            store.point_rows(near, "normal_w"),
            store.point_rows(near, "d_min_m"),
            store.point_rows(near, "d_max_m"),
            cfg.local_map_min_view_cos,
            feats.scale_factor,
            feats.n_levels,
        )
        tests.append((view, s, test))
    if not tests:
        return
    if len(views) == 1:
        _, s, test = tests[0]
        store.increase_visible(candidates[s[test.visible]])
    else:
        seen = np.zeros(candidates.size, bool)
        for _, s, test in tests:
            seen[s[test.visible]] = True
        store.increase_visible(candidates[seen])
    if wide_search:
        th = cfg.local_map_search_radius_relocalized_px
    elif feats.sensor == "rgbd":  # ORB-SLAM2 SearchLocalPoints: th = 3 for RGB-D
        th = cfg.local_map_search_radius_rgbd_px
    else:
        th = cfg.local_map_search_radius_px
    for view, s, test in tests:
        v = np.flatnonzero(test.visible)
        visible = candidates[s[v]]
        level = test.predicted_level[v]
        radius = th * radius_by_viewing_cos(test.view_cos[v]) * np.power(feats.scale_factor, level)
        # stereo/RGB-D (ORB-SLAM2 SearchByProjection(F, vpMapPoints)): a candidate with a right coordinate must agree
        # with the point's predicted one (mTrackProjXR = u - bf / z) within the search radius at the predicted level
        gate = None
        if feats.bf > 0.0 and cfg.right_coordinate_gate:
            gate = right_u_gate(feats, predicted_u_right(test.uv_px[v], test.z_m[v], feats.bf), radius)
        m = match_projected(
            feats,
            view.taken | (frame.point_ids >= 0),
            view.bounds,
            test.uv_px[v],
            store.point_rows(visible, "descriptor"),
            radius,
            level - 1,
            level,
            cfg.matcher.th_high,
            cfg.matcher.ratio_local_map,
            None,
            None,
            ratio_same_level_only=True,  # ORB-SLAM2/3 SearchByProjection: ratio only when best and second share a level
            right_gate=gate,
        )
        frame.point_ids[m.feature] = candidates[s[v[m.query]]]
