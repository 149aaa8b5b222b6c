"""Plain feature data: what a FeatureExtractor returns for one image (``Features``), and the per-keypoint observation
record a front end builds from it for a frame (``Observations``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class Features:
    """Keypoints and binary descriptors of one image.

    uv_px: (N, 2) float32, keypoint positions in the distorted (raw) image, px.
    uv_undist_px: (N, 2) float32, the same keypoints undistorted to the ideal pinhole image, px
        (equal to ``uv_px`` when the camera has no distortion).
    level: (N,) int32, pyramid level the keypoint was detected at (0 = full resolution).
    angle_deg: (N,) float32, orientation in degrees [0, 360).
    response: (N,) float32, detector response (higher = stronger corner).
    descriptors: (N, D) uint8, binary descriptors (D = 32 bytes for ORB's 256 bits).
    scale_factor: ratio between consecutive pyramid levels (ORB-SLAM: 1.2).
    n_levels: number of pyramid levels (ORB-SLAM: 8).
    """

    uv_px: NDArray[np.float32]
    uv_undist_px: NDArray[np.float32]
    level: NDArray[np.int32]
    angle_deg: NDArray[np.float32]
    response: NDArray[np.float32]
    descriptors: NDArray[np.uint8]
    scale_factor: float
    n_levels: int

    def __len__(self) -> int:
        return int(self.uv_px.shape[0])

    def level_scale(self) -> NDArray[np.float64]:
        """(N,) the scale of each keypoint's level: scale_factor ** level."""
        return np.power(self.scale_factor, self.level.astype(np.float64))

    def level_sigma2(self) -> NDArray[np.float64]:
        """(N,) px^2, measurement variance of each keypoint: scale_factor ** (2 * level) (ORB-SLAM)."""
        return np.power(self.scale_factor, 2.0 * self.level.astype(np.float64))


@dataclass(frozen=True)
class Observations(Features):
    """The per-keypoint observation record of a frame or keyframe: one shape for every sensor.

    A front end (``slamkit.interfaces.FrontEnd``) builds it from a sensor packet; Frame and KeyFrame carry it.
    On top of the extractor's ``Features`` (raw pixel ``uv_px``, ``level``, ``angle_deg``, ``response``,
    ``descriptors``) it holds what the camera and the sensor say about each keypoint (the model:
    stella_vslam's ``data/frame_observation``):

    uv_undist_px: (N, 2) float32 px, the point in the *pipeline's image*, where the pipeline matches and projects
        (``Camera.project_image``): the undistorted pinhole image for a pinhole camera (ORB-SLAM2/3), the raw
        keypoint itself for a Kannala-Brandt camera (ORB-SLAM3 keeps fisheye keypoints distorted). The name is
        the one the pipeline has always read.
    bearing: (N, 3) float64, the unit ray of each keypoint in the camera frame (``Camera.unproject_image``).
    u_right_px: (N,) float32 px, the keypoint's u coordinate in the rectified right image (stereo, or virtual
        right from depth for RGB-D: u - bf / depth); NaN where the sensor gives none (monocular).
    depth_m: (N,) float32 m, the keypoint's depth along the optical axis (stereo or RGB-D); NaN where unknown.
    bf: baseline times fx of the rectified pair, m px (0 for a monocular sensor).
    th_depth_m: close/far threshold, m (ORB-SLAM2 Frame::mThDepth = bf * ThDepth / fx): a keypoint with a depth
        below it is *close* (its depth is trusted); inf for a monocular sensor.
    sensor: "mono", "stereo" or "rgbd", the front end that built the record (ORB-SLAM2 switches a few search radii
        on it: mSensor).

    Two cameras (a non-rectified stereo pair, ORB-SLAM3 sec. I-B; its Frame's second-camera constructor): the
    record holds the keypoints of both images, camera 1's (the body camera, whose pose is the frame's T_c_w) first,
    then camera 2's, each kept as it is in its own camera's pipeline image (``uv_undist_px``, ``bearing`` in its own
    camera frame; no rectification):

    n_left: ORB-SLAM3's Nleft, the number of camera 1's keypoints (indices [0, n_left)); camera 2's are
        [n_left, N). -1 for a one-camera record (monocular, RGB-D, rectified stereo).
    stereo_match: (N,) int64 or None, the index of the other camera's keypoint matched to this one by stereo
        triangulation (ORB-SLAM3 mvLeftToRightMatch / mvRightToLeftMatch in one array of record indices), -1 for
        none; None for a one-camera record.
    xyz_c1: (N, 3) float64 m or None, the triangulated point of a stereo match in camera 1's frame at both of its
        keypoints (ORB-SLAM3 mvStereo3Dpoints), NaN elsewhere; None for a one-camera record. ``depth_m`` of a
        matched camera-1 keypoint is its z (ORB-SLAM3 mvDepth); camera 2's keypoints have no depth (NaN).
    camera_2: the second camera (a ``slamkit.interfaces.Camera``: camera 2's keypoints are in its pipeline image) or
        None for a one-camera record (ORB-SLAM3 Frame::mpCamera2).
    T_c2_c1: (4, 4) float64 or None, the rig's fixed extrinsic mapping camera-1 points into camera 2 (ORB-SLAM3
        mTrl; the inverse of the dataset's T_l_r); None for a one-camera record.
    """

    bearing: NDArray[np.float64]
    u_right_px: NDArray[np.float32]
    depth_m: NDArray[np.float32]
    bf: float = 0.0
    th_depth_m: float = float("inf")
    sensor: str = "mono"
    n_left: int = -1
    stereo_match: NDArray[np.int64] | None = None
    xyz_c1: NDArray[np.float64] | None = None
    camera_2: Any = None
    T_c2_c1: NDArray[np.float64] | None = None

    @property
    def two_cameras(self) -> bool:
        """True for a record of a non-rectified pair (keypoints of two cameras, ``n_left`` >= 0)."""
        return self.n_left >= 0

    def stereo_partner(self) -> NDArray[np.int64]:
        """(N,) int64: for a camera-1 keypoint of a two-camera record, the record index of its camera-2 stereo
        match (ORB-SLAM3 Nleft + mvLeftToRightMatch[i]), else -1 (camera 2's keypoints, unmatched ones, and every
        keypoint of a one-camera record)."""
        out = np.full(len(self), -1, np.int64)
        if self.n_left >= 0 and self.stereo_match is not None:
            out[: self.n_left] = self.stereo_match[: self.n_left]
        return out

    def camera_index(self) -> NDArray[np.int64]:
        """(N,) int64: 0 for camera 1's keypoints, 1 for camera 2's (all 0 in a one-camera record)."""
        out = np.zeros(len(self), np.int64)
        if self.n_left >= 0:
            out[self.n_left :] = 1
        return out

    @staticmethod
    def monocular(features: Features, bearing: NDArray[np.float64]) -> Observations:
        """The record of a monocular image: ``features`` and their bearings (N, 3); no right coordinate or depth."""
        n = len(features)
        return Observations(
            uv_px=features.uv_px,
            uv_undist_px=features.uv_undist_px,
            level=features.level,
            angle_deg=features.angle_deg,
            response=features.response,
            descriptors=features.descriptors,
            scale_factor=features.scale_factor,
            n_levels=features.n_levels,
            bearing=np.asarray(bearing, dtype=np.float64).reshape(n, 3),
            u_right_px=np.full(n, np.nan, np.float32),
            depth_m=np.full(n, np.nan, np.float32),
            bf=0.0,
        )

    def is_close(self) -> NDArray[np.bool_]:
        """(N,) bool: keypoints with a depth in (0, th_depth_m) (ORB-SLAM2's close points)."""
        d = self.depth_m
        return np.isfinite(d) & (d > 0) & (d < self.th_depth_m)

    def unproject_stereo(
        self, idx: NDArray[np.int64], T_w_c: NDArray[np.float64], K: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """(M, 3) m world points of keypoints ``idx`` with a depth (ORB-SLAM2 Frame::UnprojectStereo): the undistorted
        keypoint back-projected at its depth through the pinhole K (3, 3), then mapped by T_w_c (4, 4). A two-camera
        record's stereo points are its triangulated ``xyz_c1`` (ORB-SLAM3 Frame::UnprojectStereoFishEye), K unused."""
        if self.xyz_c1 is not None:
            p1 = np.asarray(self.xyz_c1[idx], np.float64).reshape(-1, 3)
            out1: NDArray[np.float64] = p1 @ T_w_c[:3, :3].T + T_w_c[:3, 3]
            return out1
        uv = self.uv_undist_px[idx].astype(np.float64)
        z = self.depth_m[idx].astype(np.float64)
        x = (uv[:, 0] - K[0, 2]) * z / K[0, 0]
        y = (uv[:, 1] - K[1, 2]) * z / K[1, 1]
        p_c = np.stack([x, y, z], axis=1)
        out: NDArray[np.float64] = p_c @ T_w_c[:3, :3].T + T_w_c[:3, 3]
        return out

    def is_stereo(self) -> NDArray[np.bool_]:
        """(N,) bool: keypoints with a right coordinate (a stereo or RGB-D measurement)."""
        return np.isfinite(self.u_right_px)
