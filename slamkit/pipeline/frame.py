"""A tracked frame: features of one image, its pose estimate and its map-point matches."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from slamkit.features import Observations
from slamkit.interfaces import Camera
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

    @staticmethod
    def create(index: int, timestamp_s: float, camera: Camera, features: Observations, bounds: ImageBounds) -> Frame:
        n = len(features)
        grid = FeatureGrid.build(
            features.uv_undist_px,
            features.level,
            int(np.ceil(bounds.max_u)),
            int(np.ceil(bounds.max_v)),
            GRID_CELL_PX,
        )
        return Frame(
            index, timestamp_s, camera, features, bounds, grid, None, np.full(n, -1, np.int64), np.zeros(n, bool)
        )

    def n_matched(self) -> int:
        return int(np.count_nonzero((self.point_ids >= 0) & ~self.outlier))
