"""The monocular front end (``frontend=mono``): ORB features of the image, their point in the pipeline's image
and their bearings from the camera model; no right coordinate, no depth."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import cv2
import numpy as np

from slamkit.features import Observations
from slamkit.interfaces import Camera, FeatureExtractor
from slamkit.sensors import FrameData


class MonocularFrontEnd:
    """Builds the observation record of a monocular frame.

    extractor: the configured feature extractor (config group ``features``). init_extractor: the one used on the
    frames of a monocular initialisation (ORB-SLAM3's Tracking constructor: 5 x the features, ORB-SLAM2's 2 x; the
    app builds it from ``pipeline.tracking.init_feature_factor``); None: the same extractor.
    """

    #: the monocular front end reads no depth: the app has the dataset skip depth maps (every colour frame is used)
    uses_depth: ClassVar[bool] = False

    def __init__(self, extractor: FeatureExtractor, init_extractor: FeatureExtractor | None = None) -> None:
        self.extractor = extractor
        self.init_extractor = init_extractor or extractor

    @property
    def n_levels(self) -> int:
        return int(self.extractor.n_levels)

    @property
    def scale_factor(self) -> float:
        return float(self.extractor.scale_factor)

    def observe(self, data: FrameData, camera: Camera, initializing: bool = False) -> Observations:
        """data.image (H, W) uint8 -> the record: raw keypoints ``uv_px``; ``uv_undist_px`` in the pipeline's image
        (undistorted through a pinhole camera, the raw keypoint for a fisheye one); unit bearings; NaN right
        coordinate and depth."""
        features = (self.init_extractor if initializing else self.extractor).extract(data.image, camera)
        if not camera.image_undistorted:
            features = dataclasses.replace(features, uv_undist_px=features.uv_px.copy())
        bearing = camera.unproject_image(features.uv_undist_px.astype(np.float64))
        return Observations.monocular(features, bearing)

    def warm_up(self, camera: Camera) -> None:
        """Run the extractors once on a textured image of the camera's size and throw the result away.

        The first extraction loads the compiled kernels (numba's on-disk cache) and starts thread pools: 20-30 ms
        once, which a timed run should not spend on its first frame."""
        rng = np.random.default_rng(0)
        noise = rng.integers(0, 256, size=(camera.height, camera.width), dtype=np.uint8)
        blurred = np.asarray(cv2.GaussianBlur(noise, (0, 0), 2.0), dtype=np.float64)
        # stretched back to 0..255: blurring leaves little contrast, and FAST must find corners
        image = np.clip((blurred - blurred.mean()) * 8.0 + 128.0, 0, 255).astype(np.uint8)
        for extractor in {id(e): e for e in (self.init_extractor, self.extractor)}.values():
            extractor.extract(image, camera)
