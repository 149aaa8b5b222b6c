"""Non-rectified stereo through the SLAM pipeline (``frontend=stereo_rig``; ORB-SLAM3 sec. I-B, its Tracking with
Nleft, LocalMapping and LocalBundleAdjustment with EdgeSE3ProjectXYZToBody): the map starts from the first frame's
stereo points (each observed by both keypoints of its stereo match), tracking matches map points in both cameras
and poses the frame with both, and local BA has the second camera's observations as residuals of their own."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from slamkit.api import System, open_system
from slamkit.eval.metrics import compute_ate
from slamkit.pipeline.bundle import snapshot_bundle
from slamkit.pipeline.outcomes import TrackingOutcome, TrackingState
from slamkit.problems import BundleProblem

#: the synthetic room through a pinhole pair (the dataset's default cameras, no rectification used)
RIG = ["frontend=stereo_rig", "dataset.stereo=true", "runner=sequential", "runner.progress=false"]


def _run(overrides: list[str], tmp_path: Path) -> tuple[System, list[TrackingOutcome]]:
    system = open_system(overrides, output_dir=tmp_path)
    log = system.run_dataset()
    return system, list(log.tracking)


def test_pinhole_rig_on_the_room_tracks_every_frame_with_both_cameras(tmp_path: Path) -> None:
    system, outcomes = _run([*RIG, "dataset.max_frames=60"], tmp_path)
    # every frame tracked from the first (one-frame initialisation from the stereo points)
    assert outcomes[0].initialized_map
    assert all(o.state == TrackingState.OK for o in outcomes)
    gt = system.dataset.ground_truth
    assert gt is not None
    ate = compute_ate(gt, system.trajectory(), align="se3")
    assert ate.rmse_m < 0.01  # metric scale from the rig: SE(3) alignment; measured 0.56 cm
    store = system.atlas.active
    with store.read():
        first = store.get_keyframe(min(store.keyframe_ids()))
        feats = first.features
        assert feats.two_cameras and feats.n_left > 0
        own = np.flatnonzero(first.point_ids >= 0)
        # the first keyframe's points sit at camera-1 keypoints with a stereo match: observed by both cameras, which
        # ORB-SLAM's Observations() counts twice
        stereo = own[(own < feats.n_left) & (feats.stereo_partner()[own] >= 0)]
        assert stereo.size > 200
        counts = store.point_rows(first.point_ids[stereo], "n_observations_orbslam")
        n_kf = store.point_rows(first.point_ids[stereo], "n_observations")
        assert np.all(counts - n_kf >= 1)  # this keyframe's observation counts 2
        # local BA's problem over the map: camera-2 rows (the partners) fit as well as camera 1's
        kf_ids = sorted(store.keyframe_ids())
        snap = snapshot_bundle(store, kf_ids[1:], kf_ids[:1], store.point_ids())
    p = snap.problem
    assert p.camera_index is not None and p.T_c2_c1 is not None and p.intrinsics2 is not None
    second = p.camera_index == 1
    assert second.sum() > 300
    err = _reprojection_px(p)
    assert np.median(err[second]) < 1.0 and np.median(err[~second]) < 1.0
    # tracking used camera 2: the last frame has matches among the second camera's keypoints
    frame = system.runner.tracker.current_frame
    assert frame is not None
    n_left = frame.features.n_left
    assert np.count_nonzero(frame.point_ids[n_left:] >= 0) > 50
    system.close()


def _reprojection_px(p: BundleProblem) -> NDArray[np.float64]:
    """(E,) px reprojection error of each observation of a pinhole bundle problem (camera 2's through T_c2_c1)."""
    assert p.camera_index is not None and p.T_c2_c1 is not None and p.intrinsics2 is not None
    T = p.T_c_w[p.obs_pose]
    cam = p.camera_index
    T = np.where((cam == 1)[:, None, None], p.T_c2_c1[p.obs_pose] @ T, T)
    intr = np.where((cam == 1)[:, None], p.intrinsics2[p.obs_pose], p.intrinsics[p.obs_pose])
    X = p.xyz_w[p.obs_point]
    Xc = np.einsum("eij,ej->ei", T[:, :3, :3], X) + T[:, :3, 3]
    u = intr[:, 0] * Xc[:, 0] / Xc[:, 2] + intr[:, 2]
    v = intr[:, 1] * Xc[:, 1] / Xc[:, 2] + intr[:, 3]
    out: NDArray[np.float64] = np.hypot(u - p.uv_px[:, 0], v - p.uv_px[:, 1])
    return out
