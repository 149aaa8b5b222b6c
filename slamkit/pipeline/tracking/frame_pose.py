"""Motion-only BA of a frame against the map points it matched (ORB-SLAM PoseOptimization, appendix), shared by
every step of tracking (V-B, V-C, V-D): the problem is built from the frame's matches, the outliers are marked."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from slamkit.interfaces import MapStore
from slamkit.pipeline.bundle import intrinsics_of, problem_camera, rig_fields
from slamkit.pipeline.config import TrackingConfig
from slamkit.pipeline.frame import Frame
from slamkit.problems import PoseOnlyProblem, PoseOnlyResult

F64 = NDArray[np.float64]


class PoseRefiner:
    """Runs ``optimize_pose`` (the compiled motion-only BA or an optimizer backend's) on a frame's matches.

    The caller holds the map's read lock (point positions are read from the store)."""

    def __init__(
        self, cfg: TrackingConfig, store: MapStore, optimize_pose: Callable[[PoseOnlyProblem], PoseOnlyResult]
    ) -> None:
        self.cfg = cfg
        self.store = store
        self.optimize_pose = optimize_pose

    def optimize(self, frame: Frame, T_init: F64) -> int:
        """Motion-only BA from T_init (4, 4) T_c_w on the frame's matches (``frame.point_ids >= 0``; a two-camera
        frame's camera-2 matches are residuals through camera 2 at T_c2_c1 T_c_w, ORB-SLAM3
        EdgeSE3ProjectXYZOnlyPoseToBody): sets
        ``frame.T_c_w`` and ``frame.outlier``; returns the inlier count."""
        idx = np.flatnonzero(frame.point_ids >= 0)
        frame.outlier[:] = False
        if idx.size < 3:
            return 0
        xyz = self.store.point_rows(frame.point_ids[idx], "xyz_w")
        feats = frame.features
        problem = PoseOnlyProblem(
            T_c_w_init=T_init,
            xyz_w=xyz,
            uv_px=feats.uv_undist_px[idx].astype(np.float64),
            u_right_px=feats.u_right_px[idx].astype(np.float64),
            level=feats.level[idx].astype(np.int64),
            intrinsics=intrinsics_of(frame.camera.K),
            bf=feats.bf,
            scale_factor=feats.scale_factor,
            chi2_mono=self.cfg.chi2.mono,
            chi2_stereo=self.cfg.chi2.stereo,
            rounds=self.cfg.pose_rounds,
            iterations_per_round=self.cfg.pose_iterations_per_round,
            **problem_camera(frame.camera),
            **rig_fields(feats, idx),
        )
        result = self.optimize_pose(problem)
        frame.T_c_w = result.T_c_w
        frame.outlier[idx] = ~result.inliers
        return int(result.inliers.sum())

    @staticmethod
    def discard_outliers(frame: Frame) -> int:
        """Forget the matches the last optimization marked as outliers; returns the matches left."""
        frame.point_ids[frame.outlier] = -1
        frame.outlier[:] = False
        return int(np.count_nonzero(frame.point_ids >= 0))
