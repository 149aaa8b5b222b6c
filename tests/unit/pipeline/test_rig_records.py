"""Two-camera records in the pipeline's bookkeeping (ORB-SLAM3 Frame/KeyFrame with Nleft; MapPoint's tuple<left,
right>): slamkit records a point at its camera-1 keypoint and lets the stereo match stand for the camera-2 one."""

from __future__ import annotations

import numpy as np

from slamkit.features import Observations
from slamkit.geometry.camera import PinholeCamera
from slamkit.map.entities import observation_weight
from slamkit.pipeline.frame import Frame, ImageBounds, camera_views, with_stereo_partners

CAM = PinholeCamera(640, 480, 400.0, 400.0, 320.0, 240.0)


def _record() -> Observations:
    """3 camera-1 keypoints, 2 camera-2 keypoints; 0 <-> 3 and 2 <-> 4 are stereo matches."""
    n = 5
    T_c2_c1 = np.eye(4)
    T_c2_c1[0, 3] = -0.1
    xyz = np.full((n, 3), np.nan)
    xyz[[0, 3]] = [0.1, 0.2, 2.0]
    xyz[[2, 4]] = [-0.3, 0.0, 4.0]
    return Observations(
        uv_px=np.zeros((n, 2), np.float32),
        uv_undist_px=np.zeros((n, 2), np.float32),
        level=np.zeros(n, np.int32),
        angle_deg=np.zeros(n, np.float32),
        response=np.ones(n, np.float32),
        descriptors=np.zeros((n, 32), np.uint8),
        scale_factor=1.2,
        n_levels=8,
        bearing=np.tile([0.0, 0.0, 1.0], (n, 1)),
        u_right_px=np.full(n, np.nan, np.float32),
        depth_m=np.array([2.0, np.nan, 4.0, np.nan, np.nan], np.float32),
        bf=40.0,
        th_depth_m=3.5,
        sensor="stereo",
        n_left=3,
        stereo_match=np.array([3, -1, 4, 0, 2], np.int64),
        xyz_c1=xyz,
        camera_2=CAM,
        T_c2_c1=T_c2_c1,
    )


def test_a_stereo_point_stands_at_both_keypoints_and_counts_twice() -> None:
    rec = _record()
    assert rec.stereo_partner().tolist() == [3, -1, 4, -1, -1]
    assert with_stereo_partners(rec, np.array([7, 8, 9, -1, 5])).tolist() == [7, 8, 9, 7, 5]  # 4 keeps its own
    # Observations(): a camera-1 keypoint with a stereo match is two observations (ORB-SLAM3 adds 1 per camera)
    assert [observation_weight(rec, i) for i in range(5)] == [2, 1, 2, 1, 1]
    # its stereo points are the triangulated ones, whatever the camera model (UnprojectStereoFishEye)
    T_w_c = np.eye(4)
    T_w_c[:3, 3] = [1.0, 2.0, 3.0]
    xyz = rec.unproject_stereo(np.array([0, 2]), T_w_c, np.eye(3))
    assert np.allclose(xyz, [[1.1, 2.2, 5.0], [0.7, 2.0, 7.0]])


def test_projection_searches_look_into_each_camera_among_its_own_keypoints() -> None:
    rec = _record()
    bounds = ImageBounds.of(CAM)
    frame = Frame.create(0, 0.0, CAM, rec, bounds, bounds)
    T = np.eye(4)
    T[2, 3] = 1.0
    one, two = camera_views(frame, T)
    assert one.camera is CAM and np.array_equal(one.T_c_w, T)
    assert one.taken.tolist() == [False, False, False, True, True]
    assert two.taken.tolist() == [True, True, True, False, False]
    assert rec.T_c2_c1 is not None and np.allclose(two.T_c_w, rec.T_c2_c1 @ T)  # camera 2 at T_c2_c1 T_c_w (ORB-SLAM3 mTrl)
