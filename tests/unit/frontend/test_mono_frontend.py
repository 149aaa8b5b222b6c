"""frontend=mono: the default config builds it through the registry, and its observation record is what the
camera model says: keypoints in the pipeline's image (undistorted through a pinhole camera, raw for a fisheye one),
unit bearings that project back onto them, no right coordinate or depth; initialisation frames use the extractor
with twice the features (ORB-SLAM's Tracking constructor)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from reference_cameras import EUROC, TUMVI

from slamkit.config import compose_config
from slamkit.features import Observations
from slamkit.frontend.mono import MonocularFrontEnd
from slamkit.interfaces import Camera, FrontEnd
from slamkit.plugins import ComponentRegistry
from slamkit.sensors import FrameData


def textured(width: int, height: int, seed: int = 0) -> np.ndarray:
    """A blurred-noise grey image with plenty of FAST corners."""
    noise = np.random.default_rng(seed).integers(0, 256, size=(height, width), dtype=np.uint8)
    blurred = np.asarray(cv2.GaussianBlur(noise, (0, 0), 2.0), dtype=np.float64)
    return np.clip((blurred - blurred.mean()) * 8.0 + 128.0, 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def frontend() -> FrontEnd:
    registry = ComponentRegistry.discover()
    cfg = compose_config([], registry=registry)
    assert cfg.frontend._target_ == "slamkit.frontend.mono.MonocularFrontEnd"
    extractor = registry.instantiate("features", cfg.features)
    node = {str(k): v for k, v in cfg.features.items()}
    node["n_features"] = 2 * int(node["n_features"])
    built = registry.instantiate(
        "frontend", cfg.frontend, extractor=extractor, init_extractor=registry.instantiate("features", node)
    )
    assert isinstance(built, MonocularFrontEnd) and isinstance(built, FrontEnd)
    assert registry.get("frontend", "mono").distribution.startswith("slamkit ")
    return built


def check_record(record: Observations, camera: Camera) -> None:
    n = len(record)
    assert n > 200
    assert record.bearing.shape == (n, 3) and record.bearing.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(record.bearing, axis=1), 1.0, atol=1e-12)
    assert record.u_right_px.shape == (n,) and np.all(np.isnan(record.u_right_px))
    assert record.depth_m.shape == (n,) and np.all(np.isnan(record.depth_m))
    assert record.bf == 0.0 and not record.is_stereo().any()
    # the bearings project back onto the keypoints of the pipeline's image
    uv, valid = camera.project_image(record.bearing)
    assert valid.all()
    np.testing.assert_allclose(uv, record.uv_undist_px, atol=1e-3)


def test_pinhole_record_is_undistorted(frontend: FrontEnd) -> None:
    image = textured(EUROC.width, EUROC.height)
    record = frontend.observe(FrameData(0, 0.0, image), EUROC)
    check_record(record, EUROC)
    assert isinstance(frontend, MonocularFrontEnd)
    features = frontend.extractor.extract(image, EUROC)
    np.testing.assert_array_equal(record.uv_undist_px, features.uv_undist_px)
    np.testing.assert_array_equal(record.uv_px, features.uv_px)
    np.testing.assert_array_equal(record.descriptors, features.descriptors)
    assert np.abs(record.uv_undist_px - record.uv_px).max() > 5.0  # the lens really is distorted
    assert (record.scale_factor, record.n_levels) == (frontend.scale_factor, frontend.n_levels) == (1.2, 8)


def test_fisheye_record_stays_in_the_raw_image(frontend: FrontEnd) -> None:
    image = textured(TUMVI.width, TUMVI.height, seed=1)
    record = frontend.observe(FrameData(0, 0.0, image), TUMVI)
    check_record(record, TUMVI)
    np.testing.assert_array_equal(record.uv_undist_px, record.uv_px)
    np.testing.assert_allclose(record.bearing, TUMVI.unproject(record.uv_px.astype(np.float64)), atol=1e-12)


def test_initialisation_frames_get_twice_the_features(frontend: FrontEnd) -> None:
    image = textured(EUROC.width, EUROC.height, seed=2)
    normal = frontend.observe(FrameData(0, 0.0, image), EUROC)
    initial = frontend.observe(FrameData(0, 0.0, image), EUROC, initializing=True)
    assert len(initial) > 1.5 * len(normal)
    check_record(initial, EUROC)
