"""Camera settings per dataset (issue 14 items 3 and 4).

- A dataset whose camera ORB-SLAM has settings for brings them: KITTI gets 2000 features (ORB-SLAM2/3
  KITTI04-12.yaml) with the README's plain ``dataset=kitti``; an ORB-SLAM settings file (``dataset.settings``) sets
  the extractor's features, scale factor, levels and FAST thresholds as well as the camera; a ``features.*`` value
  given on the command line beats both.
- A monocular run reads every colour frame of a TUM sequence (no depth association unless the front end uses depth).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from omegaconf import OmegaConf

from slamkit.app import build_components
from slamkit.config import compose_config
from slamkit.plugins import ComponentRegistry

REGISTRY = ComponentRegistry.discover()
FR1 = "tum_rgbd/rgbd_dataset_freiburg1_xyz"


def _build(overrides: list[str]) -> tuple[dict[str, object], object]:
    cfg = compose_config(overrides, registry=REGISTRY)
    return build_components(cfg, REGISTRY), cfg


def _extractor_settings(extractor: object) -> tuple[int, float, int, int, int]:
    return (
        extractor.n_features,  # type: ignore[attr-defined]
        extractor.scale_factor,  # type: ignore[attr-defined]
        extractor.n_levels,  # type: ignore[attr-defined]
        extractor.ini_fast_threshold,  # type: ignore[attr-defined]
        extractor.min_fast_threshold,  # type: ignore[attr-defined]
    )


def test_plain_kitti_gets_orbslams_kitti_extractor(shared_datasets: Path) -> None:
    built, cfg = _build(["dataset=kitti", f"dataset.root={shared_datasets}/kitti", "dataset.max_frames=2"])
    assert _extractor_settings(built["features"]) == (2000, 1.2, 8, 20, 7)
    # the run's config.yaml records what was used, not the interpolation
    assert OmegaConf.to_container(cfg.features, resolve=False)["n_features"] == 2000  # type: ignore[index]


def test_command_line_features_beat_the_datasets(shared_datasets: Path) -> None:
    built, _ = _build(
        ["dataset=kitti", f"dataset.root={shared_datasets}/kitti", "dataset.max_frames=2", "features.n_features=1500"]
    )
    # only the key given on the command line differs from KITTI's settings
    assert _extractor_settings(built["features"]) == (1500, 1.2, 8, 20, 7)


def test_settings_file_sets_extractor_and_camera(shared_datasets: Path, tmp_path: Path) -> None:
    settings = tmp_path / "kitti_custom.yaml"
    settings.write_text(
        "%YAML:1.0\n"
        'File.version: "1.0"\n'
        'Camera.type: "PinHole"\n'
        "Camera1.fx: 700.0\nCamera1.fy: 701.0\nCamera1.cx: 600.0\nCamera1.cy: 180.0\n"
        "Camera.width: 1241\nCamera.height: 376\nCamera.fps: 10\n"
        "ORBextractor.nFeatures: 3000\nORBextractor.scaleFactor: 1.25\nORBextractor.nLevels: 6\n"
        "ORBextractor.iniThFAST: 15\nORBextractor.minThFAST: 5\n"
    )
    base = ["dataset=kitti", f"dataset.root={shared_datasets}/kitti", "dataset.max_frames=2"]
    built, _ = _build([*base, f"dataset.settings={settings}"])
    assert _extractor_settings(built["features"]) == (3000, 1.25, 6, 15, 5)
    assert built["dataset"].camera.K[0, 0] == 700.0  # type: ignore[attr-defined]
    built, _ = _build([*base, f"dataset.settings={settings}", "features.min_fast_threshold=9"])
    assert _extractor_settings(built["features"]) == (3000, 1.25, 6, 15, 9)


def test_opencv_extractor_takes_the_datasets_settings_too(shared_datasets: Path) -> None:
    built, _ = _build(
        ["features=opencv_orb", "dataset=kitti", f"dataset.root={shared_datasets}/kitti", "dataset.max_frames=2"]
    )
    assert built["features"].n_features == 2000  # type: ignore[attr-defined]


def test_synthetic_world_keeps_the_extractor_defaults() -> None:
    cfg = compose_config([], registry=REGISTRY)
    assert (cfg.features.n_features, cfg.features.ini_fast_threshold) == (1000, 20)  # ORB-SLAM sec. VIII


def test_malformed_orb_extractor_block_is_named(shared_datasets: Path) -> None:
    from slamkit.errors import ConfigError

    with pytest.raises(ConfigError, match=r"dataset\.orb_extractor\.n_levels"):
        _build(["dataset=kitti", f"dataset.root={shared_datasets}/kitti", "dataset.orb_extractor.n_levels=0"])


def test_monocular_tum_run_reads_every_colour_frame(shared_datasets: Path) -> None:
    root = shared_datasets / FR1
    built, cfg = _build(["dataset=tum_rgbd", f"dataset.root={root}"])
    dataset = built["dataset"]
    # fr1_xyz: 798 colour frames, depth maps only for the first 300 -> every colour frame, none with depth
    assert len(dataset) == 798  # type: ignore[arg-type]
    assert cfg.dataset.use_depth is False
    assert dataset[0].depth_m is None and dataset[797].image is not None  # type: ignore[index]
    # depth asked for explicitly: colour frames are paired with depth maps as TUM's associate.py does
    built, _ = _build(["dataset=tum_rgbd", f"dataset.root={root}", "dataset.use_depth=true"])
    assert len(built["dataset"]) < 798  # type: ignore[arg-type]
    assert built["dataset"][0].depth_m is not None  # type: ignore[index]
