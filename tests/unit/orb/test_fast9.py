"""fast9.py's compiled FAST-9/16 equals cv2.FastFeatureDetector bit for bit (corners, order, scores), and the
ORB-SLAM extractor gives identical output with either FAST backend."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray
from slamkit_orb.fast9 import fast9_corners
from slamkit_orb.grid_fast import GridFast
from slamkit_orb.orbslam_extractor import OrbSlamExtractor
from slamkit_orb.patterns import textured_image, uneven_texture_image
from slamkit_orb.pyramid import build_pyramid, level_sizes

from slamkit.config import compose_config
from slamkit.errors import ConfigError
from slamkit.plugins import ComponentRegistry

U8 = NDArray[np.uint8]
THRESHOLDS = (1, 7, 20, 60, 254)


def _opencv(image: U8, threshold: int) -> tuple[NDArray[np.int32], NDArray[np.float32]]:
    """cv2.FastFeatureDetector (9/16, non-maximum suppression) as arrays; checks that pt is a whole pixel."""
    detector = cv2.FastFeatureDetector.create(
        threshold=threshold, nonmaxSuppression=True, type=cv2.FAST_FEATURE_DETECTOR_TYPE_9_16
    )
    keypoints = detector.detect(image)
    if not keypoints:
        return np.zeros((0, 2), np.int32), np.zeros(0, np.float32)
    pt = np.asarray(cv2.KeyPoint.convert(keypoints), np.float32)
    xy = pt.astype(np.int32)
    assert np.array_equal(xy.astype(np.float32), pt)
    return xy, np.array([k.response for k in keypoints], np.float32)


def _assert_same(image: U8, threshold: int, rect: tuple[int, int, int, int] | None = None) -> int:
    """fast9_corners == OpenCV on image (or on the crop ``rect``, shifted); returns the number of corners."""
    xy, score = fast9_corners(image, threshold, rect)
    if rect is None:
        ref_xy, ref_score = _opencv(image, threshold)
    else:
        x0, y0, x1, y1 = rect
        ref_xy, ref_score = _opencv(np.ascontiguousarray(image[y0:y1, x0:x1]), threshold)
        ref_xy = ref_xy + np.array([x0, y0], np.int32)
    assert xy.dtype == np.int32 and xy.shape == (ref_xy.shape[0], 2)
    assert score.dtype == np.float32
    np.testing.assert_array_equal(xy, ref_xy, err_msg=f"corners differ at threshold {threshold}, rect {rect}")
    np.testing.assert_array_equal(score, ref_score, err_msg=f"scores differ at threshold {threshold}, rect {rect}")
    return int(xy.shape[0])


@pytest.fixture(scope="module")
def room_frames() -> list[U8]:
    synthetic = pytest.importorskip("slamkit.io.synthetic")
    dataset = synthetic.SyntheticDataset(scene="room", depth=False, imu=False, max_frames=5)
    return [np.asarray(dataset[i].image, np.uint8) for i in range(5)]


def _levels(image: U8) -> list[U8]:
    h, w = image.shape
    return build_pyramid(image, level_sizes(w, h, 1.2, 8))


@pytest.mark.parametrize("threshold", THRESHOLDS)
def test_room_frames_every_pyramid_level(room_frames: list[U8], threshold: int) -> None:
    counts = [_assert_same(level, threshold) for frame in room_frames for level in _levels(frame)]
    assert len(counts) == 40
    if threshold <= 20:
        assert min(counts) > 500  # dense texture: every level has many corners


@pytest.mark.parametrize("threshold", [0, 1, 2, 7, 20, 33, 60, 128, 200, 254, 255])
def test_seeded_noise(threshold: int) -> None:
    rng = np.random.default_rng(1000 + threshold)
    for shape in [(480, 640), (97, 131), (64, 7), (7, 64), (33, 250)]:
        image = rng.integers(0, 256, size=shape, dtype=np.uint8)
        n = _assert_same(image, threshold)
        if threshold <= 60 and min(shape) > 7:
            assert n > 0


def test_low_contrast_noise_has_many_corners_at_the_low_thresholds() -> None:
    rng = np.random.default_rng(7)
    image = rng.integers(100, 116, size=(200, 300), dtype=np.uint8)
    assert _assert_same(image, 1) > 1000
    assert _assert_same(image, 7) > 0
    assert _assert_same(image, 20) == 0


@pytest.mark.parametrize("value", [0, 1, 128, 254, 255])
def test_flat_images_have_no_corners(value: int) -> None:
    image = np.full((60, 80), value, np.uint8)
    for threshold in (0, 1, 20, 254):
        assert _assert_same(image, threshold) == 0


def _saturated(seed: int) -> U8:
    """Blocks of 0 and 255, noise clipped to the extremes and a gradient: v + t > 255 and v - t < 0 happen."""
    rng = np.random.default_rng(seed)
    image = np.clip(rng.normal(128, 140, size=(120, 160)), 0, 255).astype(np.uint8)
    image[10:40, 20:60] = 255
    image[50:90, 70:130] = 0
    image[95:110, :] = np.linspace(0, 255, 160).astype(np.uint8)
    checker = (np.indices((16, 16)).sum(axis=0) % 2 * 255).astype(np.uint8)
    image[100:116, 130:146] = checker  # equal scores side by side: ties in the suppression
    return image


@pytest.mark.parametrize("threshold", [0, *THRESHOLDS, 255])
def test_saturated_regions_and_ties(threshold: int) -> None:
    for seed in range(3):
        _assert_same(_saturated(seed), threshold)
    binary = (np.random.default_rng(9).integers(0, 2, size=(90, 110)) * 255).astype(np.uint8)
    n = _assert_same(binary, threshold)
    assert n > 0 or threshold == 255


def test_tiny_images() -> None:
    rng = np.random.default_rng(11)
    for h in range(1, 10):
        for w in range(1, 10):
            image = rng.integers(0, 256, size=(h, w), dtype=np.uint8)
            for threshold in (1, 20):
                n = _assert_same(image, threshold)
                if h < 7 or w < 7:
                    assert n == 0


def test_empty_image_gives_no_corners() -> None:
    xy, score = fast9_corners(np.zeros((0, 0), np.uint8), 20)
    assert xy.shape == (0, 2) and xy.dtype == np.int32 and score.shape == (0,) and score.dtype == np.float32


@pytest.mark.parametrize("threshold", [1, 7, 20, 60])
def test_crops_equal_opencv_on_the_crop(room_frames: list[U8], threshold: int) -> None:
    rng = np.random.default_rng(threshold)
    for image in (room_frames[0], rng.integers(0, 256, size=(123, 157), dtype=np.uint8)):
        h, w = image.shape
        rects = [(0, 0, w, h), (5, 3, w - 2, h - 7), (1, 2, 8, 9), (3, 3, 10, 40), (0, 0, 6, 30), (w - 7, h - 7, w, h)]
        for _ in range(20):
            x0, x1 = sorted(rng.integers(0, w + 1, size=2).tolist())
            y0, y1 = sorted(rng.integers(0, h + 1, size=2).tolist())
            rects.append((x0, y0, x1, y1))
        for rect in rects:
            _assert_same(image, threshold, rect)


def test_non_contiguous_views(room_frames: list[U8]) -> None:
    image = room_frames[1]
    views = [image[17:301, 33:455], image[::2, ::3], image.T, image[::-1, ::-1], image[100:50:-1, 7:90]]
    for view in views:
        assert not view.flags.c_contiguous
        for threshold in (7, 20):
            xy, score = fast9_corners(view, threshold)
            ref_xy, ref_score = _opencv(np.ascontiguousarray(view), threshold)
            np.testing.assert_array_equal(xy, ref_xy)
            np.testing.assert_array_equal(score, ref_score)
            # OpenCV takes strided views as they are too (rows must be contiguous for it).
            if view.strides[1] == 1:
                np.testing.assert_array_equal(xy, _opencv(view, threshold)[0])


def test_scores_do_not_depend_on_the_threshold(room_frames: list[U8]) -> None:
    """A corner at 20 has the same score in a run at 7 (what grid_fast's single low-threshold run relies on);
    the suppression differs only through neighbours that are corners at 7 but not at 20."""
    xy20, score20 = fast9_corners(room_frames[2], 20)
    xy7, score7 = fast9_corners(room_frames[2], 7)
    at7 = {(int(x), int(y)): s for (x, y), s in zip(xy7, score7, strict=True)}
    strong7 = {xy: s for xy, s in at7.items() if s >= 20}
    assert strong7 == {(int(x), int(y)): s for (x, y), s in zip(xy20, score20, strict=True)}
    assert np.all(score20 >= 20) and np.all(score7 >= 7)


def _real_frames(shared_datasets: Path) -> Iterator[tuple[str, U8]]:
    tum = shared_datasets / "tum_rgbd" / "rgbd_dataset_freiburg1_xyz_first10" / "rgb"
    kitti = shared_datasets / "kitti" / "sequences" / "07" / "image_0"
    paths = sorted(tum.glob("*.png"))[:3] + sorted(kitti.glob("*.png"))[:2]
    if not paths:
        pytest.skip(f"neither {tum} nor {kitti} holds PNG frames")
    for path in paths:
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        assert image is not None, f"could not read {path}"
        yield path.name, np.asarray(image, np.uint8)


def test_real_frames_every_pyramid_level(shared_datasets: Path) -> None:
    n_frames = 0
    for _, frame in _real_frames(shared_datasets):
        n_frames += 1
        for level in _levels(frame):
            for threshold in (7, 20):
                _assert_same(level, threshold)
        assert _assert_same(frame, 1) > 0
    assert n_frames > 0


@pytest.mark.parametrize(
    ("threshold", "message"),
    [(-1, "got -1"), (256, "got 256"), (7.0, "got 7.0"), (True, "got True"), ("20", "got '20'")],
)
def test_bad_threshold_is_refused(threshold: object, message: str) -> None:
    with pytest.raises(ValueError, match=rf"fast9_corners: threshold must be an integer in \[0, 255\].*{message}"):
        fast9_corners(np.zeros((20, 20), np.uint8), cast(Any, threshold))


@pytest.mark.parametrize("image", [np.zeros((20, 20, 3), np.uint8), np.zeros((20, 20), np.float32), [[0, 1], [2, 3]]])
def test_bad_image_is_refused(image: object) -> None:
    with pytest.raises(ValueError, match=r"fast9_corners: image must be an \(H, W\) uint8 grey array"):
        fast9_corners(cast(Any, image), 20)


@pytest.mark.parametrize("rect", [(-1, 0, 10, 10), (0, 0, 21, 10), (5, 0, 4, 10), (0, 8, 10, 7)])
def test_bad_rect_is_refused(rect: tuple[int, int, int, int]) -> None:
    with pytest.raises(ValueError, match=r"rect must satisfy 0 <= x0 <= x1 <= 20 and 0 <= y0 <= y1 <= 15"):
        fast9_corners(np.zeros((15, 20), np.uint8), 20, rect)


def _grid_images(room_frames: list[U8]) -> list[U8]:
    noise = np.random.default_rng(8).integers(0, 256, size=(480, 640), dtype=np.uint8)
    return [room_frames[0], textured_image(seed=6), uneven_texture_image(seed=7), noise]


@pytest.mark.parametrize("strategy", ["whole", "cells", "auto"])
def test_grid_fast_is_the_same_with_both_backends(room_frames: list[U8], strategy: str) -> None:
    compiled, opencv = GridFast(19, 30, 20, 7, "compiled"), GridFast(19, 30, 20, 7, "opencv")
    for image in _grid_images(room_frames):
        for level in _levels(image):
            for hint in (0.0, 1.0):
                a = compiled.detect(level, cast(Any, strategy), hint)
                b = opencv.detect(level, cast(Any, strategy), hint)
                np.testing.assert_array_equal(a.xy, b.xy)
                np.testing.assert_array_equal(a.response, b.response)
                assert a.region == b.region and a.weak_share == pytest.approx(b.weak_share)


def test_grid_fast_refuses_an_unknown_backend() -> None:
    with pytest.raises(ValueError, match=r"GridFast: backend must be one of \('compiled', 'opencv'\), got 'cuda'"):
        GridFast(19, 30, 20, 7, cast(Any, "cuda"))


def _assert_same_features(image: U8, n_features: int, n_threads: int) -> int:
    ours = OrbSlamExtractor(n_features=n_features, n_threads=n_threads, fast_backend="compiled")
    theirs = OrbSlamExtractor(n_features=n_features, n_threads=n_threads, fast_backend="opencv")
    a, b = ours.extract(image), theirs.extract(image)
    for name in ("uv_px", "uv_undist_px", "level", "angle_deg", "response", "descriptors"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    return len(a)


def test_extractor_output_is_the_same_with_both_backends_on_room_frames(room_frames: list[U8]) -> None:
    for i, frame in enumerate(room_frames):
        assert _assert_same_features(frame, 1000, 1 + i % 2) == 1000


def test_extractor_output_is_the_same_with_both_backends_on_a_frame_sequence(room_frames: list[U8]) -> None:
    """The opencv backend changes its FAST strategy per level from the previous frame; outputs stay equal."""
    compiled = OrbSlamExtractor(fast_backend="compiled")
    opencv = OrbSlamExtractor(fast_backend="opencv")
    frames = [uneven_texture_image(seed=3), *room_frames[:2], uneven_texture_image(seed=4)]
    for frame in frames:
        a, b = compiled.extract(frame), opencv.extract(frame)
        np.testing.assert_array_equal(a.uv_px, b.uv_px)
        np.testing.assert_array_equal(a.descriptors, b.descriptors)


def test_extractor_output_is_the_same_with_both_backends_on_real_frames(
    tum_image: U8, kitti_image: U8, euroc_image: U8
) -> None:
    assert _assert_same_features(tum_image, 1000, 2) == 1000
    assert _assert_same_features(kitti_image, 2000, 2) == 2000
    assert _assert_same_features(euroc_image, 1000, 1) == 1000


def test_fast_backend_config() -> None:
    registry = ComponentRegistry.discover()
    cfg = compose_config(["features=orb"], registry=registry)
    extractor = registry.instantiate("features", cfg.features)
    assert isinstance(extractor, OrbSlamExtractor) and extractor.fast_backend == "compiled"
    cfg = compose_config(["features=orb", "features.fast_backend=opencv"], registry=registry)
    assert registry.instantiate("features", cfg.features).fast_backend == "opencv"
    with pytest.raises(ConfigError, match=r"features.fast_backend must be one of compiled, opencv, got 'gpu'"):
        OrbSlamExtractor(fast_backend=cast(Any, "gpu"))
