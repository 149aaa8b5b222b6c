"""Plain feature data: what a FeatureExtractor returns for one image."""

from __future__ import annotations

from dataclasses import dataclass

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
