"""The FeatureExtractor contract: every registered feature extractor must pass these tests.

Parametrized over ``ComponentRegistry.discover().components("features")``, each built from its default config node.
Images are frames of slamkit's synthetic room (real rendered texture, no files needed).

What an extractor promises (slamkit/interfaces.py FeatureExtractor, slamkit/features.py Features):
- the same image gives the same features, bit for bit (the sequential runner's determinism rests on it);
- every field has its documented shape and dtype, one row per keypoint; scale_factor / n_levels are the
  extractor's; levels are in [0, n_levels); angles in [0, 360); keypoints lie inside the image; a sensible count
  (more than 100 on a textured 640x480 frame, at most 1.1 x n_features when the extractor has that setting);
- with a camera, ``uv_undist_px`` is ``camera.undistort_points(uv_px)`` (to 1e-3 px); without one, it equals uv_px;
- a blank image gives zero features, with the right shapes and dtypes, and no error;
- the same scene rotated by 90 degrees gives the same descriptors at the corresponding keypoints (rotation
  invariance, ORB-SLAM III-A): for keypoints found at corresponding places (same level, within 1.5 px x the
  level's scale), the median Hamming distance is at most 25 bits of 256 (unrelated descriptors: ~128) and the
  orientations differ by 90 degrees (median within 5 degrees).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from slamkit.features import Features
from slamkit.geometry.camera import PinholeCamera
from slamkit.interfaces import FeatureExtractor
from slamkit.io.synthetic.dataset import SyntheticDataset
from slamkit.pipeline.matching import hamming_rows
from slamkit.plugins import ComponentRegistry

REGISTRY = ComponentRegistry.discover()
NAMES = [c.spec.name for c in REGISTRY.components("features")]
ROTATED_MEDIAN_BITS = 25
ROTATED_ANGLE_DEG = 5.0


@pytest.fixture(scope="module", params=NAMES)
def extractor(request: pytest.FixtureRequest) -> FeatureExtractor:
    node = REGISTRY.get("features", request.param).config_node()
    built: FeatureExtractor = REGISTRY.instantiate("features", node)
    return built


@pytest.fixture(scope="module")
def room() -> SyntheticDataset:
    return SyntheticDataset(scene="room", seed=0, imu=False)


@pytest.fixture(scope="module")
def image(room: SyntheticDataset) -> np.ndarray:
    return np.asarray(room[60].image)


def check_fields(feats: Features, extractor: FeatureExtractor, shape: tuple[int, int]) -> None:
    n = len(feats)
    expected: dict[str, tuple[tuple[int, ...], Any]] = {
        "uv_px": ((n, 2), np.float32),
        "uv_undist_px": ((n, 2), np.float32),
        "level": ((n,), np.int32),
        "angle_deg": ((n,), np.float32),
        "response": ((n,), np.float32),
        "descriptors": ((n, 32), np.uint8),
    }
    for name, (want_shape, dtype) in expected.items():
        value = getattr(feats, name)
        assert value.shape == want_shape and value.dtype == dtype, f"{name}: {value.shape} {value.dtype}"
    assert feats.scale_factor == extractor.scale_factor and feats.n_levels == extractor.n_levels
    assert np.all((feats.level >= 0) & (feats.level < extractor.n_levels))
    assert np.all((feats.angle_deg >= 0) & (feats.angle_deg < 360))
    h, w = shape
    uv = feats.uv_px
    assert np.isfinite(uv).all() and np.all((uv >= 0) & (uv <= [w - 1, h - 1])), "keypoints outside the image"


def check_rotation_invariance(extractor: FeatureExtractor, image: np.ndarray) -> tuple[float, float]:
    """Median Hamming distance (bits) and median |angle difference - 90 deg| of keypoints found at corresponding
    places in a square crop and the crop rotated by 90 degrees clockwise; asserts enough such pairs exist."""
    h = image.shape[0]
    x0 = (image.shape[1] - h) // 2
    crop = np.ascontiguousarray(image[:, x0 : x0 + h])
    rot = np.ascontiguousarray(cv2.rotate(crop, cv2.ROTATE_90_CLOCKWISE), dtype=np.uint8)
    a, b = extractor.extract(crop), extractor.extract(rot)
    # clockwise by 90 deg: (u, v) -> (h - 1 - v, u)
    mapped = np.c_[h - 1 - a.uv_px[:, 1], a.uv_px[:, 0]]
    dist, j = cKDTree(b.uv_px).query(mapped)
    ok = (dist <= 1.5 * a.level_scale()) & (b.level[j] == a.level)
    assert ok.sum() >= 0.2 * len(a) and ok.sum() >= 50, f"{ok.sum()} of {len(a)} keypoints found again"
    i = np.flatnonzero(ok)
    bits = hamming_rows(a.descriptors[i], b.descriptors[j[i]])
    turn = np.mod(b.angle_deg[j[i]].astype(np.float64) - a.angle_deg[i], 360.0)
    off90 = np.minimum(np.abs(turn - 90.0), np.abs(turn - 270.0))  # either orientation convention
    return float(np.median(bits)), float(np.median(off90))


def test_is_a_feature_extractor(extractor: FeatureExtractor) -> None:
    assert isinstance(extractor, FeatureExtractor)
    assert extractor.n_levels >= 1 and extractor.scale_factor >= 1.0


def test_deterministic(extractor: FeatureExtractor, image: np.ndarray) -> None:
    a, b = extractor.extract(image), extractor.extract(image.copy())
    for name in ("uv_px", "uv_undist_px", "level", "angle_deg", "response", "descriptors"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name


def test_fields_shapes_dtypes_and_ranges(extractor: FeatureExtractor, image: np.ndarray) -> None:
    feats = extractor.extract(image)
    check_fields(feats, extractor, image.shape)
    assert len(feats) > 100
    n_features = getattr(extractor, "n_features", None)
    if n_features is not None:
        assert len(feats) <= 1.1 * n_features
    assert np.array_equal(feats.uv_undist_px, feats.uv_px)  # no camera: nothing to undistort
    assert len(np.unique(feats.level)) > 1, "a pyramid: features on more than one level"


def test_undistorted_points_follow_the_camera(extractor: FeatureExtractor, image: np.ndarray) -> None:
    h, w = image.shape
    camera = PinholeCamera(w, h, 470.0, 470.0, (w - 1) / 2, (h - 1) / 2, dist=[-0.28, 0.07, 1e-3, -5e-4])
    feats = extractor.extract(image, camera)
    check_fields(feats, extractor, image.shape)
    assert len(feats) > 100
    expected = camera.undistort_points(feats.uv_px.astype(np.float64))
    assert np.allclose(feats.uv_undist_px, expected, atol=1e-3)
    assert np.abs(feats.uv_undist_px - feats.uv_px).max() > 1.0  # the distortion really moved them


@pytest.mark.parametrize("value", [0, 128, 255])
def test_blank_image_gives_no_features(extractor: FeatureExtractor, value: int) -> None:
    blank = np.full((480, 640), value, np.uint8)
    feats = extractor.extract(blank)
    assert len(feats) == 0
    check_fields(feats, extractor, blank.shape)


def test_rotated_scene_gives_matching_descriptors(extractor: FeatureExtractor, image: np.ndarray) -> None:
    bits, off90 = check_rotation_invariance(extractor, image)
    assert bits <= ROTATED_MEDIAN_BITS, f"median Hamming distance {bits} bits at corresponding keypoints"
    assert off90 <= ROTATED_ANGLE_DEG, f"orientations differ from 90 deg by {off90} deg (median)"


# ---- the suite catches a broken extractor ------------------------------------------------------------------


class _Broken:
    """Wraps an extractor and spoils one thing about its output."""

    def __init__(self, inner: FeatureExtractor, spoil: Callable[[Features], Features]) -> None:
        self.inner, self.spoil = inner, spoil
        self.n_levels, self.scale_factor = inner.n_levels, inner.scale_factor

    def extract(self, image: np.ndarray, camera: Any = None) -> Features:
        return self.spoil(self.inner.extract(image, camera))


def _no_orientation(f: Features) -> Features:
    """Descriptors computed as if every keypoint had angle 0: what an unsteered BRIEF gives."""
    from dataclasses import replace

    return replace(f, angle_deg=np.zeros_like(f.angle_deg), descriptors=np.sort(f.descriptors, axis=1))


def test_suite_fails_on_broken_extractors(image: np.ndarray) -> None:
    orb = REGISTRY.instantiate("features", REGISTRY.get("features", "orb").config_node())  # the default one
    from dataclasses import replace

    shifted = _Broken(orb, lambda f: replace(f, uv_px=f.uv_px + np.float32(700.0)))
    with pytest.raises(AssertionError, match="outside the image"):
        check_fields(shifted.extract(image), shifted, image.shape)
    wrong_level = _Broken(orb, lambda f: replace(f, level=f.level + np.int32(orb.n_levels)))
    with pytest.raises(AssertionError):
        check_fields(wrong_level.extract(image), wrong_level, image.shape)
    unsteered = _Broken(orb, _no_orientation)
    bits, off90 = check_rotation_invariance(unsteered, image)
    assert off90 > ROTATED_ANGLE_DEG  # every angle 0: the 90 degree turn is not seen
    noisy = _Broken(orb, lambda f: replace(f, descriptors=np.random.default_rng(0).permutation(f.descriptors)))
    bits, _ = check_rotation_invariance(noisy, image)
    assert bits > ROTATED_MEDIAN_BITS
