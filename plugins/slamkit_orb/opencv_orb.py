"""OpenCV's stock ORB detector/descriptor behind slamkit's FeatureExtractor interface."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from slamkit.errors import ConfigError
from slamkit.features import Features
from slamkit.interfaces import Camera


class OpenCvOrbExtractor:
    """cv2.ORB_create with ORB-SLAM's default parameters; keypoints undistorted through the camera.

    Unlike ORB-SLAM's extractor it does not spread corners over a grid, so weakly textured regions
    get few features: it is the baseline the ``orb`` extractor is compared against.
    """

    def __init__(
        self,
        n_features: int = 1000,
        scale_factor: float = 1.2,
        n_levels: int = 8,
        fast_threshold: int = 20,
        edge_threshold: int = 19,
    ) -> None:
        if n_features <= 0:
            raise ConfigError(f"features.n_features must be positive, got {n_features}")
        if scale_factor <= 1.0:
            raise ConfigError(f"features.scale_factor must be > 1, got {scale_factor}")
        if n_levels < 1:
            raise ConfigError(f"features.n_levels must be >= 1, got {n_levels}")
        self.n_features = int(n_features)
        self.scale_factor = float(scale_factor)
        self.n_levels = int(n_levels)
        self._orb = cv2.ORB.create(
            nfeatures=self.n_features,
            scaleFactor=self.scale_factor,
            nlevels=self.n_levels,
            edgeThreshold=int(edge_threshold),
            patchSize=31,
            fastThreshold=int(fast_threshold),
        )

    def extract(self, image: NDArray[np.uint8], camera: Camera | None = None) -> Features:
        """image: (H, W) uint8 grey -> Features (uv in raw px; uv_undist through ``camera`` when given)."""
        if image.ndim != 2 or image.dtype != np.uint8:
            raise ValueError(f"extract expects an (H, W) uint8 grey image, got {image.shape} {image.dtype}")
        keypoints, descriptors = self._orb.detectAndCompute(image, None)
        n = len(keypoints)
        uv = np.array([kp.pt for kp in keypoints], dtype=np.float32).reshape(n, 2)
        if camera is not None and n:
            uv_undist = camera.undistort_points(uv.astype(np.float64)).astype(np.float32)
        else:
            uv_undist = uv.copy()
        return Features(
            uv_px=uv,
            uv_undist_px=uv_undist,
            level=np.array([kp.octave for kp in keypoints], dtype=np.int32),
            angle_deg=np.array([kp.angle for kp in keypoints], dtype=np.float32),
            response=np.array([kp.response for kp in keypoints], dtype=np.float32),
            descriptors=np.asarray(descriptors, np.uint8) if descriptors is not None else np.zeros((0, 32), np.uint8),
            scale_factor=self.scale_factor,
            n_levels=self.n_levels,
        )
