"""ORB-SLAM sec. V-C: relocalization (Tracking::Relocalization): bag-of-words candidates -> BoW matches -> PnP in
RANSAC (EPnP) -> motion-only BA -> guided search for more matches -> accepted with enough inliers. Every
threshold is a ``pipeline.tracking.reloc_*`` value. The caller holds the map's read lock."""

from __future__ import annotations

import logging
from collections.abc import Callable

import cv2
import numpy as np

from slamkit.interfaces import BowDescription, MapStore, PlaceRecognizer
from slamkit.map.entities import KeyFrame
from slamkit.pipeline.config import TrackingConfig
from slamkit.pipeline.frame import Frame
from slamkit.pipeline.map_points import predict_level
from slamkit.pipeline.projection import match_projected, project_points
from slamkit.pipeline.tracking.frame_pose import PoseRefiner

log = logging.getLogger("slamkit.tracking")


def relocalize(
    frame: Frame,
    bow: BowDescription,
    store: MapStore,
    place: PlaceRecognizer,
    cfg: TrackingConfig,
    refiner: PoseRefiner,
    best_neighbors: Callable[[int, int], list[int]],
) -> int | None:
    """Try the place recognizer's candidates in order; the first that gives ``min_local_map_inliers_after_reloc``
    inliers wins. Returns its id (frame.T_c_w and frame.point_ids set), or None (frame.T_c_w None, no matches).

    store: the active map; only its keyframes are tried. best_neighbors(kf_id, n): a candidate's covisibility
    neighbours in its own map (the Atlas's ``best_neighbors``), which group the candidates; candidates of other
    maps are skipped (ORB-SLAM3 DetectRelocalizationCandidates)."""
    matcher = cfg.matcher
    for kf_id, _ in place.relocalization_candidates(bow, best_neighbors):
        if not store.has_keyframe(kf_id):
            continue
        kf = store.get_keyframe(kf_id)
        if kf.bow is None:
            continue
        valid = store.has_points(kf.point_ids)
        pairs = place.match(
            kf.features,
            kf.bow,
            frame.features,
            bow,
            matcher.ratio_relocalization,
            valid,
            None,
            max_distance=matcher.th_low,
            rotation_bins=matcher.rotation_bins,
        )
        if pairs.shape[0] < cfg.reloc_min_bow_matches:
            continue
        uv = frame.features.uv_undist_px[pairs[:, 1]].astype(np.float64)
        if not frame.camera.image_undistorted:
            # a fisheye keypoint enters EPnP as its bearing seen through K (ORB-SLAM3 solves PnP on bearings);
            # rays at or behind 90 degrees have no such pixel and are left out
            b = frame.features.bearing[pairs[:, 1]]
            ahead = b[:, 2] > 0
            pairs, b = pairs[ahead], b[ahead]
            if pairs.shape[0] < cfg.reloc_min_bow_matches:
                continue
            uv = (b[:, :2] / b[:, 2:3]) @ frame.camera.K[:2, :2].T + frame.camera.K[:2, 2]
        xyz = np.stack([store.get_point(int(kf.point_ids[i])).xyz_w for i in pairs[:, 0]])
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            xyz,
            uv,
            frame.camera.K,
            None,
            iterationsCount=cfg.reloc_pnp_ransac_iterations,
            reprojectionError=float(np.sqrt(cfg.chi2.mono)),
            confidence=cfg.reloc_pnp_ransac_confidence,
            flags=cv2.SOLVEPNP_EPNP,
        )
        if not ok or inliers is None or len(inliers) < cfg.reloc_min_pnp_inliers:
            continue
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(rvec)[0]
        T[:3, 3] = tvec.ravel()
        frame.point_ids[:] = -1
        sel = pairs[inliers.ravel()]
        frame.point_ids[sel[:, 1]] = kf.point_ids[sel[:, 0]]
        refiner.optimize(frame, T)
        good = refiner.discard_outliers(frame)
        if good < cfg.reloc_min_pnp_inliers:
            continue
        # ORB-SLAM: SearchByProjection(frame, kf, found, 10, 100), then (3, 64) if still short of 50 inliers
        searches = (
            (cfg.reloc_search_radius_px, cfg.reloc_search_max_distance),
            (cfg.reloc_search_radius_fine_px, cfg.reloc_search_max_distance_fine),
        )
        for radius, max_dist in searches:
            if good >= cfg.min_local_map_inliers_after_reloc:
                break
            added = search_keyframe_points(frame, kf, store, radius, max_dist)
            if good + added >= cfg.min_local_map_inliers_after_reloc:
                assert frame.T_c_w is not None
                refiner.optimize(frame, frame.T_c_w)
                good = refiner.discard_outliers(frame)
        if good >= cfg.min_local_map_inliers_after_reloc:
            log.info("relocalized frame %d against keyframe %d with %d inliers", frame.index, kf_id, good)
            return kf_id
    frame.point_ids[:] = -1
    frame.T_c_w = None
    return None


def search_keyframe_points(frame: Frame, kf: KeyFrame, store: MapStore, radius_px: float, max_distance: int) -> int:
    """ORB-SLAM SearchByProjection(Frame, KeyFrame): project the keyframe's points not matched yet with the frame's
    pose and match them around the projection (radius_px x scale of the predicted level, Hamming <= max_distance
    bits); the distance must lie in the point's scale-invariance range (ORB-SLAM's 0.8 d_min, 1.2 d_max).
    Returns the matches added to frame.point_ids."""
    assert frame.T_c_w is not None
    found = frame.point_ids[frame.point_ids >= 0]
    kf_ids = kf.point_ids[kf.point_ids >= 0]
    pids = kf_ids[~np.isin(kf_ids, found) & store.has_points(kf_ids)]
    if pids.size == 0:
        return 0
    feats = frame.features
    xyz = store.point_rows(pids, "xyz_w")
    uv, _, valid = project_points(frame.T_c_w, xyz, frame.camera)
    center = -frame.T_c_w[:3, :3].T @ frame.T_c_w[:3, 3]
    dist = np.linalg.norm(xyz - center, axis=1)
    d_min = store.point_rows(pids, "d_min_m")
    d_max = store.point_rows(pids, "d_max_m")
    ok = valid & (dist >= 0.8 * d_min) & (dist <= 1.2 * d_max)
    ok &= frame.bounds.contains(np.nan_to_num(uv, nan=-1e9))
    q = np.flatnonzero(ok)
    if q.size == 0:
        return 0
    level = predict_level(d_max[q], dist[q], feats.scale_factor, feats.n_levels)
    m = match_projected(
        feats,
        frame.point_ids >= 0,
        frame.bounds,
        uv[q],
        store.point_rows(pids[q], "descriptor"),
        radius_px * np.power(feats.scale_factor, level),
        level - 1,
        level + 1,
        max_distance,
        None,
        None,
        None,
    )
    frame.point_ids[m.feature] = pids[q[m.query]]
    return len(m)
