"""The RGB-D front end (``frontend=rgbd``): ORB features of the grey image, each keypoint's depth read from the
registered depth map, and the virtual right coordinate of ORB-SLAM2 (Mur-Artal & Tardos 2017, sec. III-A;
Frame::ComputeStereoFromRGBD):

- the depth d is the depth map's value at the *raw* keypoint (the depth image is registered to the raw colour
  image; ORB-SLAM2 reads ``imDepth.at<float>(v, u)`` at the distorted keypoint, the float coordinates truncated);
- where d > 0: ``depth_m = d`` and ``u_right_px = u_undist - bf / d`` (the undistorted keypoint's u);
- elsewhere NaN (a monocular observation of that keypoint);
- ``th_depth_m = bf * th_depth / fx``: keypoints closer than that are *close* (ORB-SLAM2 mThDepth).

The monocular initialisation's larger extractor is not used: RGB-D initialises from one frame (ORB-SLAM2 builds
mpIniORBextractor for monocular only).
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

import numpy as np

from slamkit.errors import DatasetError
from slamkit.features import Observations
from slamkit.frontend.mono import MonocularFrontEnd
from slamkit.interfaces import Camera, FeatureExtractor
from slamkit.sensors import FrameData


class RgbdFrontEnd(MonocularFrontEnd):
    """Builds the observation record of an RGB-D frame (colour/grey image + registered depth map in metres).

    bf: the virtual baseline times fx, m px (ORB-SLAM2 settings ``Camera.bf``; TUM1/2/3.yaml: 40, "IR projector
    baseline times fx (aprox.)"). th_depth: the close/far threshold in baselines (settings ``ThDepth``: 40).
    """

    #: the dataset reads depth maps for this front end (slamkit.app.resolve_dataset_depth)
    uses_depth: ClassVar[bool] = True

    def __init__(
        self,
        extractor: FeatureExtractor,
        init_extractor: FeatureExtractor | None = None,
        bf: float = 40.0,
        th_depth: float = 40.0,
    ) -> None:
        super().__init__(extractor, None)
        del init_extractor  # one-frame initialisation: the normal extractor (see the module docstring)
        if not bf > 0.0 or not th_depth > 0.0:
            raise ValueError(f"frontend=rgbd: bf = {bf} and th_depth = {th_depth} must be > 0")
        self.bf = float(bf)
        self.th_depth = float(th_depth)

    def bind_dataset(self, dataset: Any) -> None:
        """Take bf and ThDepth from the dataset's ORB-SLAM settings file when it gives them (``settings_bf``,
        ``settings_th_depth``: Camera.bf / Stereo.b, ThDepth), as ORB-SLAM reads them; else keep the config's."""
        bf = getattr(dataset, "settings_bf", None)
        th_depth = getattr(dataset, "settings_th_depth", None)
        if bf is not None and bf > 0.0:
            self.bf = float(bf)
        if th_depth is not None and th_depth > 0.0:
            self.th_depth = float(th_depth)

    def observe(self, data: FrameData, camera: Camera, initializing: bool = False) -> Observations:
        """data.image (H, W) uint8 and data.depth_m (H, W) float32 m (0 = unknown) -> the record with depth_m and
        u_right_px where the depth map has a positive depth at the keypoint, NaN elsewhere.

        Raises DatasetError naming the frame when it has no depth map or one of another size than the image."""
        depth = data.depth_m
        where = data.source or f"frame {data.index}"
        if depth is None:
            raise DatasetError(
                f"frontend=rgbd: frame {data.index} ({where}) has no depth map; the dataset must read depth "
                "(dataset.use_depth: true, a sequence with depth maps)"
            )
        if depth.shape != data.image.shape[:2]:
            raise DatasetError(
                f"frontend=rgbd: frame {data.index} ({where}): depth map of shape {depth.shape}, image of shape "
                f"{data.image.shape[:2]}; the depth map must be registered to the image"
            )
        obs = super().observe(data, camera, False)
        n = len(obs)
        h, w = depth.shape
        # ORB-SLAM2 ComputeStereoFromRGBD: imDepth.at<float>(v, u) at the raw keypoint (float -> int truncation)
        u = np.clip(obs.uv_px[:, 0].astype(np.int64), 0, w - 1)
        v = np.clip(obs.uv_px[:, 1].astype(np.int64), 0, h - 1)
        d = depth[v, u].astype(np.float32) if n else np.zeros(0, np.float32)
        valid = np.isfinite(d) & (d > 0)
        depth_m = np.full(n, np.nan, np.float32)
        u_right = np.full(n, np.nan, np.float32)
        depth_m[valid] = d[valid]
        u_right[valid] = (obs.uv_undist_px[valid, 0].astype(np.float64) - self.bf / d[valid]).astype(np.float32)
        fx = float(camera.K[0, 0])
        return dataclasses.replace(
            obs,
            depth_m=depth_m,
            u_right_px=u_right,
            bf=self.bf,
            th_depth_m=self.bf * self.th_depth / fx,
            sensor="rgbd",
        )
