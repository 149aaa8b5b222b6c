"""OrbSlamExtractor end to end: budget, spread, fallback, undistortion, determinism, bad input, config."""

from __future__ import annotations

from pathlib import Path
from typing import Any, cast

import numpy as np
import pytest
from numpy.typing import NDArray
from slamkit_orb.coverage import grid_coverage
from slamkit_orb.opencv_orb import OpenCvOrbExtractor
from slamkit_orb.orbslam_extractor import OrbSlamExtractor
from slamkit_orb.patterns import textured_image, uneven_texture_image

from slamkit.config import compose_config
from slamkit.errors import CalibrationError, ConfigError
from slamkit.features import Features
from slamkit.geometry.camera import KannalaBrandtCamera, PinholeCamera
from slamkit.interfaces import FeatureExtractor
from slamkit.plugins import ComponentRegistry


def _assert_well_formed(features: Features, n: int) -> None:
    assert features.uv_px.shape == (n, 2) and features.uv_px.dtype == np.float32
    assert features.uv_undist_px.shape == (n, 2) and features.uv_undist_px.dtype == np.float32
    assert features.level.shape == (n,) and features.level.dtype == np.int32
    assert features.angle_deg.shape == (n,) and features.angle_deg.dtype == np.float32
    assert features.response.shape == (n,) and features.response.dtype == np.float32
    assert features.descriptors.shape == (n, 32) and features.descriptors.dtype == np.uint8
    assert (features.scale_factor, features.n_levels) == (1.2, 8)


def test_implements_the_feature_extractor_protocol(extractor: OrbSlamExtractor) -> None:
    assert isinstance(extractor, FeatureExtractor)
    features = extractor.extract(textured_image(seed=30))
    _assert_well_formed(features, 1000)
    assert np.all((features.angle_deg >= 0) & (features.angle_deg < 360))
    assert np.all(features.response >= 7)


def test_each_level_fills_its_share_of_the_budget(extractor: OrbSlamExtractor) -> None:
    features = extractor.extract(textured_image(seed=31))
    assert np.bincount(features.level, minlength=8).tolist() == [217, 181, 151, 126, 105, 87, 73, 60]


def test_keypoints_are_level_pixels_scaled_to_level_0(extractor: OrbSlamExtractor) -> None:
    features = extractor.extract(textured_image(seed=32))
    scale = 1.2 ** features.level.astype(np.float64)
    level_xy = features.uv_px / scale[:, None]
    np.testing.assert_allclose(level_xy, np.rint(level_xy), atol=1e-3)
    # No keypoint within the edge threshold of its level's border.
    assert np.all(level_xy >= 19 - 1e-3)
    sizes = np.array([[640, 480], [533, 400], [444, 333], [370, 278], [309, 231], [257, 193], [214, 161], [179, 134]])
    assert np.all(level_xy < sizes[features.level] - 19 + 1e-3)


def test_quadtree_spreads_features_better_than_opencv_orb() -> None:
    """Strong texture in the top-left block, weaker (still above FAST 20) elsewhere; fallback disabled so
    only the quadtree makes the difference."""
    image = uneven_texture_image(seed=30, weak_grey_range=(100, 135))
    ours = OrbSlamExtractor(min_fast_threshold=20).extract(image)
    baseline = OpenCvOrbExtractor().extract(image)
    ours_cov, base_cov = grid_coverage(ours.uv_px, 640, 480), grid_coverage(baseline.uv_px, 640, 480)
    assert ours_cov > 0.5 and ours_cov > 2 * base_cov
    # Share of the features outside the strong block (the block is 9 % of the image).
    ours_out = np.mean((ours.uv_px[:, 0] > 200) | (ours.uv_px[:, 1] > 150))
    base_out = np.mean((baseline.uv_px[:, 0] > 200) | (baseline.uv_px[:, 1] > 150))
    assert ours_out > 0.4 and ours_out > 4 * base_out


def test_fallback_threshold_gives_features_in_low_contrast_cells(extractor: OrbSlamExtractor) -> None:
    image = uneven_texture_image(seed=34)  # outside the top-left block: contrast <= 14 grey levels
    features = extractor.extract(image)
    low_contrast = (features.uv_px[:, 0] > 200) | (features.uv_px[:, 1] > 150)
    assert np.count_nonzero(low_contrast) > 300
    assert grid_coverage(features.uv_px, 640, 480) > 0.45
    for without_fallback in (OrbSlamExtractor(min_fast_threshold=20), OpenCvOrbExtractor()):
        other = without_fallback.extract(image)
        assert np.count_nonzero((other.uv_px[:, 0] > 200) | (other.uv_px[:, 1] > 150)) == 0


def test_undistorted_coordinates_come_from_the_camera(extractor: OrbSlamExtractor) -> None:
    image = textured_image(seed=35)
    camera = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0, [-0.3, 0.1, 0.001, -0.002])
    features = extractor.extract(image, camera)
    plain = extractor.extract(image)
    np.testing.assert_array_equal(features.uv_px, plain.uv_px)
    expected = camera.undistort_points(features.uv_px.astype(np.float64))
    np.testing.assert_allclose(features.uv_undist_px, expected, atol=1e-3)
    corner = np.linalg.norm(features.uv_px - [320.0, 240.0], axis=1) > 300
    assert np.all(np.linalg.norm(features.uv_undist_px[corner] - features.uv_px[corner], axis=1) > 10)
    np.testing.assert_array_equal(plain.uv_undist_px, plain.uv_px)

    fisheye = KannalaBrandtCamera(640, 480, 300.0, 300.0, 320.0, 240.0, [0.05, -0.01, 0.002, 0.0])
    fish = extractor.extract(image, fisheye)
    np.testing.assert_allclose(
        fish.uv_undist_px, fisheye.undistort_points(fish.uv_px.astype(np.float64)), atol=1e-3, rtol=1e-6
    )


def test_keypoints_beyond_the_distortion_models_range_are_dropped(extractor: OrbSlamExtractor) -> None:
    image = textured_image(seed=36)
    # k1 = -0.6: the model folds back at r = 0.745 (distorted radius ~150 px): the image corners are beyond it.
    camera = PinholeCamera(640, 480, 300.0, 300.0, 320.0, 240.0, [-0.6, 0.0, 0.0, 0.0])
    plain = extractor.extract(image)
    valid = np.all(np.isfinite(camera.undistort_points(plain.uv_px.astype(np.float64))), axis=1)
    assert 0 < np.count_nonzero(valid) < len(plain)
    features = extractor.extract(image, camera)
    np.testing.assert_array_equal(features.uv_px, plain.uv_px[valid])
    np.testing.assert_array_equal(features.descriptors, plain.descriptors[valid])
    assert np.all(np.isfinite(features.uv_undist_px))


def test_camera_of_another_size_is_refused(extractor: OrbSlamExtractor) -> None:
    camera = PinholeCamera(752, 480, 458.0, 457.0, 367.0, 248.0)
    with pytest.raises(
        CalibrationError, match=r"image is 640x480 px but the camera \(pinhole\) is calibrated for 752x480"
    ):
        extractor.extract(textured_image(seed=37), camera)


def test_output_is_deterministic_and_independent_of_threads() -> None:
    image = uneven_texture_image(seed=38)
    runs = [OrbSlamExtractor(n_threads=2).extract(image) for _ in range(2)]
    runs.append(OrbSlamExtractor(n_threads=1).extract(image))
    # The extractor picks its FAST strategy per level from the previous frame: results must not depend on it.
    warmed = OrbSlamExtractor()
    warmed.extract(textured_image(seed=40))  # dense: few weak cells -> per-cell strategy next
    runs.append(warmed.extract(image))
    for other in runs[1:]:
        for name in ("uv_px", "uv_undist_px", "level", "angle_deg", "response", "descriptors"):
            np.testing.assert_array_equal(getattr(runs[0], name), getattr(other, name))


def test_extract_with_pyramid_gives_extracts_features_and_the_levels_they_were_found_on() -> None:
    """The stereo front end's call (issue 16): the features of ``extract`` whether the levels are shared out to the
    extractor's threads or all found in the calling thread, and the packed pyramid holds the level images the
    keypoints come from (a keypoint's level position is inside its level image)."""
    image = uneven_texture_image(seed=41)
    camera = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0, [0.05, -0.02, 0.0, 0.0])
    extractor = OrbSlamExtractor(n_threads=2)
    reference = extractor.extract(image, camera)
    assert len(reference) > 500
    for threaded in (True, False):
        features, pyramid = extractor.extract_with_pyramid(image, camera, threaded=threaded)
        for name in ("uv_px", "uv_undist_px", "level", "angle_deg", "response", "descriptors"):
            np.testing.assert_array_equal(getattr(features, name), getattr(reference, name))
        pixels, offsets, widths, heights = pyramid.packed()
        assert len(pyramid.levels) == 8 and offsets.shape == widths.shape == heights.shape == (8,)
        np.testing.assert_array_equal(pyramid.levels[0], image)
        for level, view in enumerate(pyramid.levels):
            assert view.shape == (heights[level], widths[level]) and np.shares_memory(view, pixels)
        scale = np.float32(1.2) ** features.level.astype(np.float32)
        xy = np.rint(features.uv_px / scale[:, None]).astype(np.int64)
        assert np.all(xy[:, 0] < widths[features.level]) and np.all(xy[:, 1] < heights[features.level])
    with pytest.raises(CalibrationError, match="calibrated for 752x480"):
        extractor.extract_with_pyramid(image, PinholeCamera(752, 480, 458.0, 457.0, 367.0, 248.0))


@pytest.mark.parametrize(
    "image",
    [
        np.zeros((480, 640), np.uint8),
        np.full((480, 640), 200, np.uint8),
        np.zeros((0, 0), np.uint8),
        np.zeros((1, 1), np.uint8),
        np.random.default_rng(0).integers(0, 256, (20, 30), dtype=np.uint8),
        np.random.default_rng(1).integers(0, 256, (38, 500), dtype=np.uint8),
    ],
    ids=["black", "flat", "empty", "1x1", "20x30-noise", "38x500-noise"],
)
def test_blank_and_tiny_images_give_no_features(extractor: OrbSlamExtractor, image: NDArray[np.uint8]) -> None:
    _assert_well_formed(extractor.extract(image), 0)


def test_small_image_uses_the_levels_it_can() -> None:
    features = OrbSlamExtractor(n_threads=1).extract(textured_image(seed=39, width=120, height=90))
    assert len(features) > 0
    # Level 5 is 48x36 px: its detection area (19 px border) has no room for the FAST circle.
    assert 0 in features.level and set(features.level.tolist()) <= {0, 1, 2, 3, 4}


@pytest.mark.parametrize(
    "image",
    [np.zeros((48, 64, 3), np.uint8), np.zeros((48, 64), np.float32), [[0, 1], [2, 3]]],
    ids=["colour", "float", "list"],
)
def test_non_grey_images_are_refused(extractor: OrbSlamExtractor, image: object) -> None:
    with pytest.raises(ValueError, match=r"image must be an \(H, W\) uint8 grey array"):
        extractor.extract(cast(Any, image))


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"n_features": 0}, r"features.n_features must be >= 1, got 0"),
        ({"n_features": 10.5}, r"features.n_features must be an integer"),
        ({"scale_factor": 1.0}, r"features.scale_factor must be a number > 1"),
        ({"n_levels": 0}, r"features.n_levels must be in \[1, 32\]"),
        ({"min_fast_threshold": 25}, r"features.min_fast_threshold must be in \[1, 20\], got 25"),
        ({"ini_fast_threshold": 300}, r"features.ini_fast_threshold must be in \[1, 254\]"),
        ({"patch_size": 15}, r"features.patch_size must be in \[31, 31\]"),
        ({"edge_threshold": 10}, r"features.edge_threshold must be >= 15, got 10"),
        ({"cell_size_px": 3}, r"features.cell_size_px must be >= 7"),
        ({"n_threads": 0}, r"features.n_threads must be in \[1, 64\]"),
    ],
)
def test_bad_config_names_the_key(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        OrbSlamExtractor(**cast(dict[str, Any], kwargs))


def test_features_orb_is_selectable_by_config() -> None:
    registry = ComponentRegistry.discover()
    assert registry.get("features", "orb").plugin == "orb"
    cfg = compose_config(["features=orb"], registry=registry)
    extractor = registry.instantiate("features", cfg.features)
    assert isinstance(extractor, OrbSlamExtractor)
    assert (extractor.n_features, extractor.scale_factor, extractor.n_levels) == (1000, 1.2, 8)
    assert (extractor.ini_fast_threshold, extractor.min_fast_threshold, extractor.cell_size_px) == (20, 7, 30)
    assert (extractor.edge_threshold, extractor.patch_size, extractor.half_patch_size) == (19, 31, 15)
    kitti = compose_config(["features=orb", "+experiment=kitti07"], registry=registry)
    assert registry.instantiate("features", kitti.features).n_features == 2000


@pytest.mark.parametrize(("name", "n_features"), [("tum_image", 1000), ("euroc_image", 1000), ("kitti_image", 2000)])
def test_real_images_fill_the_budget_and_beat_opencvs_coverage(
    name: str, n_features: int, request: pytest.FixtureRequest
) -> None:
    image: NDArray[np.uint8] = request.getfixturevalue(name)
    h, w = image.shape
    ours = OrbSlamExtractor(n_features=n_features).extract(image)
    baseline = OpenCvOrbExtractor(n_features=n_features).extract(image)
    assert len(ours) == n_features
    assert grid_coverage(ours.uv_px, w, h) > grid_coverage(baseline.uv_px, w, h) + 0.3


def test_euroc_frame_with_its_calibration(euroc_image: NDArray[np.uint8], shared_datasets: Path) -> None:
    """EuRoC cam0's radial-tangential model (sensor.yaml) moves border keypoints by tens of pixels."""
    sensor = (shared_datasets / "euroc" / "V1_01_easy" / "mav0" / "cam0" / "sensor.yaml").read_text()
    assert "458.654, 457.296, 367.215, 248.375" in sensor
    camera = PinholeCamera(
        752, 480, 458.654, 457.296, 367.215, 248.375, [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
    )
    features = OrbSlamExtractor().extract(euroc_image, camera)
    assert len(features) > 990
    shift = np.linalg.norm(features.uv_undist_px - features.uv_px, axis=1)
    radius = np.linalg.norm(features.uv_px - [367.215, 248.375], axis=1)
    assert shift[radius > 350].min() > 20 and shift[radius < 30].max() < 0.5
