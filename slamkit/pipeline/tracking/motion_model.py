"""ORB-SLAM sec. V-B, first case: the constant-velocity motion model (Tracking::TrackWithMotionModel) and the
last frame's pose following its reference keyframe (Tracking::UpdateLastFrame).

The caller holds the map's read lock. Poses are (4, 4) ``T_c_w``; the velocity is ``T_cur_last``."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from slamkit.geometry.se3 import invert_T, orthonormalized_T
from slamkit.interfaces import MapStore
from slamkit.pipeline.config import TrackingConfig
from slamkit.pipeline.frame import Frame, camera_views, with_stereo_partners
from slamkit.pipeline.projection import match_projected, predicted_u_right, project_points, right_u_gate
from slamkit.pipeline.tracking.frame_pose import PoseRefiner

F64 = NDArray[np.float64]


def update_last_frame(store: MapStore, last: Frame, T_l_r: F64 | None) -> None:
    """ORB-SLAM UpdateLastFrame: the last frame's pose follows its reference keyframe (T_l_r (4, 4): its pose
    relative to that keyframe when it was tracked), so corrections of the map (local BA, loop closing) reach the
    motion model's starting point. A stereo/RGB-D last frame that became a keyframe takes that keyframe's points
    (the ones local mapping made from its depths among them)."""
    if last.ref_kf_id is None or not store.has_keyframe(last.ref_kf_id):
        return
    kf = store.get_keyframe(last.ref_kf_id)
    if kf.features.bf > 0.0 and kf.frame_index == last.index:
        # stereo/RGB-D: the last frame is that keyframe; it tracks the points made from its depths too (ORB-SLAM2
        # CreateNewKeyFrame sets mCurrentFrame.mvpMapPoints[i] to each new point)
        last.point_ids = with_stereo_partners(kf.features, kf.point_ids)  # a two-camera keyframe: both keypoints
        last.outlier[:] = False
    if T_l_r is None:
        return
    last.T_c_w = T_l_r @ kf.T_c_w


def pose_relative_to_reference(store: MapStore, frame: Frame) -> F64 | None:
    """(4, 4) T_c_r of a tracked frame relative to its reference keyframe (None when that keyframe is not in the
    map, e.g. the keyframe just made from the frame, which local mapping has not inserted yet)."""
    ref = frame.ref_kf_id
    if ref is None or frame.T_c_w is None or not store.has_keyframe(ref):
        return None
    return frame.T_c_w @ invert_T(store.get_keyframe(ref).T_c_w)


def velocity(frame: Frame, last: Frame | None) -> F64 | None:
    """(4, 4) T_cur_last of two consecutive tracked frames (None when the last one has no pose);
    re-orthonormalised: products of poses drift off SO(3) and optimizers reject them."""
    if frame.T_c_w is None or last is None or last.T_c_w is None:
        return None
    return orthonormalized_T(frame.T_c_w @ invert_T(last.T_c_w))


def track_with_motion_model(
    frame: Frame, last: Frame, T_cur_last: F64, store: MapStore, cfg: TrackingConfig, refiner: PoseRefiner
) -> bool:
    """V-B: predict the pose with constant velocity, search the last frame's points around their projection
    (radius th * scale of their level, twice as wide when fewer than ``min_motion_model_matches``), optimize the
    pose; success with at least ``min_inliers_after_pose_opt`` inliers (sets frame.point_ids, frame.T_c_w)."""
    assert last.T_c_w is not None
    T_pred = orthonormalized_T(T_cur_last @ last.T_c_w)
    valid = np.flatnonzero(store.has_points(last.point_ids) & ~last.outlier)
    if valid.size == 0:
        return False
    feats = frame.features
    if feats.two_cameras:
        # a point matched at both cameras' keypoints of the last frame is searched once per camera, from its first
        # (camera-1) keypoint's level and angle
        _, first = np.unique(last.point_ids[valid], return_index=True)
        valid = valid[np.sort(first)]
    pids = last.point_ids[valid]
    xyz = store.point_rows(pids, "xyz_w")
    desc = store.point_rows(pids, "descriptor")
    radius = cfg.motion_model_search_radius_stereo_px if feats.sensor == "stereo" else cfg.motion_model_search_radius_px
    searches = []
    for view in camera_views(frame, T_pred):
        uv, z, inside = project_points(view.T_c_w, xyz, view.camera)
        inside &= view.bounds.contains(np.where(np.isfinite(uv), uv, -1e9))
        q = np.flatnonzero(inside)
        last_level = last.features.level[valid[q]].astype(np.int64)
        scale = np.power(feats.scale_factor, last_level)
        lo, hi = last_level - 1, last_level + 1
        if feats.bf > 0.0:
            # ORB-SLAM2 SearchByProjection(CurrentFrame, LastFrame), stereo/RGB-D: the current camera centre in the
            # last camera (tlc); more than a baseline forward: points look bigger, searched at the last level or
            # coarser; more than a baseline backward: at the last level or finer
            centre = -T_pred[:3, :3].T @ T_pred[:3, 3]
            z_cur = float(last.T_c_w[2, :3] @ centre + last.T_c_w[2, 3])
            baseline = feats.bf / float(frame.camera.K[0, 0])
            if z_cur > baseline:
                hi = np.full_like(last_level, feats.n_levels - 1)
                lo = last_level
            elif -z_cur > baseline:
                lo = np.zeros_like(last_level)
                hi = last_level
        u_right = predicted_u_right(uv[q], z[q], feats.bf) if feats.bf > 0.0 and cfg.right_coordinate_gate else None
        searches.append((view, uv, q, scale, lo, hi, u_right))
    for th in (radius, 2.0 * radius):
        frame.point_ids[:] = -1
        n_matches = 0
        for view, uv, q, scale, lo, hi, u_right in searches:
            # stereo/RGB-D (ORB-SLAM2 SearchByProjection(CurrentFrame, LastFrame)): a candidate with a right
            # coordinate must agree with the predicted u - bf / z within the search radius
            gate = None if u_right is None else right_u_gate(feats, u_right, th * scale)
            m = match_projected(
                feats,
                view.taken,
                view.bounds,
                uv[q],
                desc[q],
                th * scale,
                lo,
                hi,
                cfg.matcher.th_high,
                None,
                last.features.angle_deg[valid[q]].astype(np.float64),
                cfg.matcher.rotation_bins,
                right_gate=gate,
            )
            frame.point_ids[m.feature] = pids[q[m.query]]
            n_matches += len(m)
        if n_matches >= cfg.min_motion_model_matches:
            break
    if np.count_nonzero(frame.point_ids >= 0) < cfg.min_motion_model_matches:
        return False
    refiner.optimize(frame, T_pred)
    return refiner.discard_outliers(frame) >= cfg.min_inliers_after_pose_opt
