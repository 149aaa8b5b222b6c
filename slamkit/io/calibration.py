"""Choosing a reader's camera: its own calibration, a ``camera:`` config mapping, or ``settings: PATH``."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from slamkit.errors import ConfigError
from slamkit.geometry.camera import camera_from_config
from slamkit.interfaces import Camera
from slamkit.io.orbslam_settings import OrbExtractorSettings, OrbSlamSettings, load_orbslam_settings

#: The keys of a dataset's ``orb_extractor`` block (ORB-SLAM's ``ORBextractor.*`` settings for its camera).
ORB_EXTRACTOR_KEYS = ("n_features", "scale_factor", "n_levels", "ini_th_fast", "min_th_fast")


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


def orb_extractor_from_options(
    orb_extractor: Mapping[str, Any] | None, settings: OrbSlamSettings | None
) -> OrbExtractorSettings | None:
    """The ORB extractor settings a dataset brings for its camera (``Dataset.orb_settings``), or None.

    settings: a loaded ``dataset.settings`` file; its ``ORBextractor.*`` block wins. orb_extractor: the
    ``dataset.orb_extractor`` mapping (ORB-SLAM's settings file for this camera, written in the dataset's config:
    n_features, scale_factor, n_levels, ini_th_fast, min_th_fast), used when the file has none. The app gives them
    to every ``features.*`` key the command line did not set (docs/configs.md, "Camera settings per dataset").
    Raises ConfigError naming ``dataset.orb_extractor`` for a malformed mapping.
    """
    if settings is not None and settings.orb is not None:
        return settings.orb
    if orb_extractor is None:
        return None
    if not isinstance(orb_extractor, Mapping):
        raise ConfigError(
            f"dataset.orb_extractor: expected a mapping of {', '.join(ORB_EXTRACTOR_KEYS)}, got {orb_extractor!r}"
        )
    keys = {str(k) for k in orb_extractor}
    if keys != set(ORB_EXTRACTOR_KEYS):
        missing = sorted(set(ORB_EXTRACTOR_KEYS) - keys)
        extra = sorted(keys - set(ORB_EXTRACTOR_KEYS))
        raise ConfigError(
            f"dataset.orb_extractor: missing {missing}, unknown {extra}; expected {list(ORB_EXTRACTOR_KEYS)}"
        )
    values = {str(k): v for k, v in orb_extractor.items()}
    for key in ("n_features", "n_levels", "ini_th_fast", "min_th_fast"):
        v = values[key]
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ConfigError(f"dataset.orb_extractor.{key}: expected a positive integer, got {v!r}")
    scale = values["scale_factor"]
    if isinstance(scale, bool) or not isinstance(scale, int | float) or not float(scale) > 1.0:
        raise ConfigError(f"dataset.orb_extractor.scale_factor: expected a number > 1, got {scale!r}")
    return OrbExtractorSettings(
        n_features=int(values["n_features"]),
        scale_factor=float(scale),
        n_levels=int(values["n_levels"]),
        ini_th_fast=int(values["ini_th_fast"]),
        min_th_fast=int(values["min_th_fast"]),
    )
