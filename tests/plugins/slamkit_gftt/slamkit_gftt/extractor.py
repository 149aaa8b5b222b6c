"""Shi-Tomasi (good features to track) corners with ORB descriptors, single scale."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from slamkit.features import Features
from slamkit.interfaces import Camera


class GfttOrbExtractor:
    n_levels = 1
    scale_factor = 1.2

    def __init__(self, n_features: int = 500, quality_level: float = 0.01, min_distance_px: float = 8.0) -> None:
        self.n_features = n_features
        self.quality_level = quality_level
        self.min_distance_px = min_distance_px
        self._orb = cv2.ORB.create(nfeatures=n_features)

    def extract(self, image: NDArray[np.uint8], camera: Camera | None = None) -> Features:
        corners = cv2.goodFeaturesToTrack(image, self.n_features, self.quality_level, self.min_distance_px)
        pts = corners.reshape(-1, 2) if corners is not None else np.zeros((0, 2), np.float32)
        keypoints = [cv2.KeyPoint(float(x), float(y), 31.0) for x, y in pts]
        keypoints, desc = self._orb.compute(image, keypoints)
        n = len(keypoints)
        uv = np.array([k.pt for k in keypoints], np.float32).reshape(n, 2)
        uv_undist = camera.undistort_points(uv.astype(np.float64)).astype(np.float32) if camera and n else uv
        return Features(
            uv_px=uv,
            uv_undist_px=uv_undist,
            level=np.zeros(n, np.int32),
            angle_deg=np.array([k.angle for k in keypoints], np.float32),
            response=np.array([k.response for k in keypoints], np.float32),
            descriptors=desc if desc is not None else np.zeros((0, 32), np.uint8),
            scale_factor=self.scale_factor,
            n_levels=self.n_levels,
        )
