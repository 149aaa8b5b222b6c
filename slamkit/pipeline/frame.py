"""A tracked frame: features of one image, its pose estimate and its map-point matches."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from slamkit.features import Observations
from slamkit.interfaces import Camera
from slamkit.map.entities import KeyFrame
from slamkit.pipeline.matching import FeatureGrid

F64 = NDArray[np.float64]

#: ORB-SLAM's frame grid cell, px (64 x 48 cells on 640 x 480).
GRID_CELL_PX = 10.0


@dataclass(frozen=True)
class ImageBounds:
    """Bounds of the pipeline's image (``Camera.image_bounds``), px: where a projected point counts as inside."""

    min_u: float
    max_u: float
    min_v: float
    max_v: float

    @staticmethod
    def of(camera: Camera) -> ImageBounds:
        """The camera's pipeline image: for a distorted pinhole camera the undistorted corners bound the valid
        region (ORB-SLAM ComputeImageBounds); for a fisheye camera, the raw image."""
        return ImageBounds(*camera.image_bounds())

    def contains(self, uv_px: F64) -> NDArray[np.bool_]:
        """uv_px: (N, 2) -> (N,) bool."""
        u, v = uv_px[:, 0], uv_px[:, 1]
        return (u >= self.min_u) & (u < self.max_u) & (v >= self.min_v) & (v < self.max_v)


@dataclass
class Frame:
    """A frame being tracked.

    T_c_w: (4, 4) world -> camera once estimated. point_ids: (N,) int64 map point per feature (-1 none).
    outlier: (N,) bool, features whose match pose optimization rejected. grid: the keypoints of the
    pipeline's image bucketed for window searches. features: the per-keypoint observation record.
    bounds2: the second camera's image bounds for a two-camera record (``features.camera_2``), else None.
    A two-camera frame's ``point_ids`` run over both cameras' keypoints (ORB-SLAM3 mvpMapPoints over Nleft + Nright):
    a point may be matched at a camera-1 and a camera-2 keypoint at once.
    """

    index: int
    timestamp_s: float
    camera: Camera
    features: Observations
    bounds: ImageBounds
    grid: FeatureGrid
    T_c_w: F64 | None = None
    point_ids: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    outlier: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    ref_kf_id: int | None = None
    bounds2: ImageBounds | None = None

    @staticmethod
    def create(
        index: int,
        timestamp_s: float,
        camera: Camera,
        features: Observations,
        bounds: ImageBounds,
        bounds2: ImageBounds | None = None,
    ) -> Frame:
        n = len(features)
        grid = FeatureGrid.build(
            features.uv_undist_px,
            features.level,
            int(np.ceil(bounds.max_u)),
            int(np.ceil(bounds.max_v)),
            GRID_CELL_PX,
        )
        return Frame(
            index,
            timestamp_s,
            camera,
            features,
            bounds,
            grid,
            None,
            np.full(n, -1, np.int64),
            np.zeros(n, bool),
            None,
            bounds2,
        )

    def n_matched(self) -> int:
        return int(np.count_nonzero((self.point_ids >= 0) & ~self.outlier))


def with_stereo_partners(features: Observations, point_ids: NDArray[np.int64]) -> NDArray[np.int64]:
    """(N,) int64: ``point_ids`` of a two-camera record with each camera-1 keypoint's point also at its camera-2
    stereo match where that has none (ORB-SLAM3 StereoInitialization / CreateNewKeyFrame set mvpMapPoints at i and at
    Nleft + mvLeftToRightMatch[i]); a keyframe records the camera-1 index only (the store keeps one keypoint per
    keyframe and point) and its stereo matches stand for the camera-2 observations. One-camera records: unchanged."""
    out = np.array(point_ids, np.int64, copy=True)
    if not features.two_cameras:
        return out
    partner = features.stereo_partner()
    i = np.flatnonzero((partner >= 0) & (out >= 0))
    j = partner[i]
    free = out[j] < 0
    out[j[free]] = out[i[free]]
    return out


@dataclass(frozen=True)
class CameraView:
    """One camera of a frame for a projection search: its pose ``T_c_w`` (4, 4) (camera 2's: T_c2_c1 @ the frame's),
    its model and image bounds, and ``taken`` (N,) bool marking the keypoints a search into it must skip (the
    other camera's; none for a one-camera frame). ``index``: 0 or 1."""

    index: int
    T_c_w: F64
    camera: Camera
    bounds: ImageBounds
    taken: NDArray[np.bool_]


def camera_views(frame: Frame, T_c_w: F64) -> list[CameraView]:
    """The cameras a projection search of ``frame`` at pose T_c_w (4, 4) looks into: the frame's camera, and for a
    two-camera record the second one (ORB-SLAM3 SearchByProjection / SearchLocalPoints: a second isInFrustum with
    mpCamera2 and matching among the right keypoints only)."""
    feats = frame.features
    n = len(feats)
    if not feats.two_cameras or feats.camera_2 is None or feats.T_c2_c1 is None or frame.bounds2 is None:
        return [CameraView(0, T_c_w, frame.camera, frame.bounds, np.zeros(n, bool))]
    cam = feats.camera_index()
    return [
        CameraView(0, T_c_w, frame.camera, frame.bounds, cam != 0),
        CameraView(1, np.asarray(feats.T_c2_c1, np.float64) @ T_c_w, feats.camera_2, frame.bounds2, cam != 1),
    ]


def keyframe_cameras(kf: KeyFrame) -> tuple[int, ...]:
    """The cameras of a keyframe: (0,) or, for a two-camera record, (0, 1)."""
    return (0, 1) if kf.features.two_cameras and kf.features.camera_2 is not None else (0,)


def keyframe_view(kf: KeyFrame, camera: int) -> KeyFrame:
    """``kf`` seen as camera ``camera`` alone: itself for 0; for 1 a stand-in keyframe (same id, record, points and bag
    of words) posed at T_c2_c1 T_c_w with the second camera's model, where triangulation computes with camera 2
    (ORB-SLAM3 CreateNewMapPoints: GetRightPose / mpCamera2 for a right keypoint). Never put in a map."""
    feats = kf.features
    if camera == 0:
        return kf
    assert feats.T_c2_c1 is not None and feats.camera_2 is not None
    return KeyFrame(
        kf.id,
        kf.frame_index,
        kf.timestamp_s,
        np.asarray(feats.T_c2_c1, np.float64) @ kf.T_c_w,
        feats.camera_2,
        feats,
        kf.point_ids,
        kf.bow,
    )
