"""ORB-SLAM sec. V-B, fallback: tracking the reference keyframe (Tracking::TrackReferenceKeyFrame) when there is
no motion model or it found too few matches. The caller holds the map's read lock."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from slamkit.interfaces import BowDescription, MapStore, PlaceRecognizer
from slamkit.pipeline.config import TrackingConfig
from slamkit.pipeline.frame import Frame
from slamkit.pipeline.matching import hamming_matrix, resolve_one_to_one, rotation_consistent
from slamkit.pipeline.tracking.frame_pose import PoseRefiner

F64 = NDArray[np.float64]


def track_reference_keyframe(
    frame: Frame,
    reference_kf_id: int | None,
    T_init: F64,
    store: MapStore,
    cfg: TrackingConfig,
    refiner: PoseRefiner,
    place: PlaceRecognizer | None,
    frame_bow: Callable[[], BowDescription],
) -> bool:
    """Match the reference keyframe's map points by descriptor (nearest/second ratio ``ratio_reference_kf``,
    rotation consistency) and optimize the pose from T_init (4, 4) T_c_w, the last frame's. ORB-SLAM restricts the
    candidates with the bag of words (``place``; frame_bow computes the frame's once); without a place recognizer
    all features are candidates. Success with ``min_reference_kf_matches`` matches and
    ``min_inliers_after_pose_opt`` inliers."""
    if reference_kf_id is None or not store.has_keyframe(reference_kf_id):
        return False
    kf = store.get_keyframe(reference_kf_id)
    valid = store.has_points(kf.point_ids)
    feats_kf = np.flatnonzero(valid)
    if feats_kf.size == 0 or len(frame.features) == 0:
        return False
    if place is not None and kf.bow is not None:
        pairs = place.match(
            kf.features,
            kf.bow,
            frame.features,
            frame_bow(),
            cfg.matcher.ratio_reference_kf,
            valid,
            None,
            max_distance=cfg.matcher.th_low,
            rotation_bins=cfg.matcher.rotation_bins,
        )
        frame.point_ids[:] = -1
        frame.point_ids[pairs[:, 1]] = kf.point_ids[pairs[:, 0]]
        n_matches = int(pairs.shape[0])
    else:
        dist = hamming_matrix(kf.features.descriptors[feats_kf], frame.features.descriptors)
        order = np.argsort(dist, axis=1, kind="stable")
        best = order[:, 0]
        rows = np.arange(feats_kf.size)
        d1 = dist[rows, best]
        d2 = dist[rows, order[:, 1]] if dist.shape[1] > 1 else np.full(feats_kf.size, 1 << 30)
        ok = (d1 <= cfg.matcher.th_low) & (d1 < cfg.matcher.ratio_reference_kf * d2)
        q = np.flatnonzero(ok)
        keep = resolve_one_to_one(q, best[q], d1[q])
        q = q[keep]
        angle_diff = kf.features.angle_deg[feats_kf[q]].astype(np.float64) - frame.features.angle_deg[best[q]]
        q = q[rotation_consistent(angle_diff, cfg.matcher.rotation_bins)]
        frame.point_ids[:] = -1
        frame.point_ids[best[q]] = kf.point_ids[feats_kf[q]]
        n_matches = int(q.size)
    if n_matches < cfg.min_reference_kf_matches:
        return False
    refiner.optimize(frame, T_init)
    return refiner.discard_outliers(frame) >= cfg.min_inliers_after_pose_opt
