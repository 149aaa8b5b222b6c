"""Choosing a reader's camera: its own calibration, a ``camera:`` config mapping, or ``settings: PATH``."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from slamkit.errors import ConfigError
from slamkit.geometry.camera import camera_from_config
from slamkit.interfaces import Camera
from slamkit.io.orbslam_settings import OrbSlamSettings, load_orbslam_settings


def load_settings(settings: str | Path | None, image_size: tuple[int, int] | None) -> OrbSlamSettings | None:
    """``dataset.settings``: an ORB-SLAM settings file, or None. image_size (W, H) fills a missing size."""
    if settings is None or str(settings) == "":
        return None
    return load_orbslam_settings(Path(settings), image_size=image_size)


def camera_from_options(
    camera: Mapping[str, Any] | None, settings: OrbSlamSettings | None, image_size: tuple[int, int]
) -> tuple[Camera, str]:
    """Camera of a reader that has no calibration of its own (folder, video) -> (camera, its source).

    camera: ``dataset.camera`` mapping for ``camera_from_config``; width/height default to the images'
    (W, H). Exactly one of ``dataset.camera`` and ``dataset.settings`` must be given.
    """
    if camera is not None and settings is not None:
        raise ConfigError("dataset.camera and dataset.settings are both set; give one camera source")
    if settings is not None:
        return settings.camera, str(settings.path)
    if camera is None:
        raise ConfigError(
            "dataset.camera (a mapping: model, fx, fy, cx, cy, ...) or dataset.settings (an ORB-SLAM "
            "settings file) is required: this dataset has no calibration of its own"
        )
    if not isinstance(camera, Mapping):
        raise ConfigError(f"dataset.camera: expected a mapping of camera parameters, got {camera!r}")
    cfg = {str(k): v for k, v in camera.items()}
    cfg.setdefault("width", image_size[0])
    cfg.setdefault("height", image_size[1])
    return camera_from_config(cfg, key="dataset.camera"), "config dataset.camera"
