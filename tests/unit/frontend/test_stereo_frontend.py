"""frontend=stereo (ORB-SLAM2 Frame::ComputeStereoMatches): on the synthetic room's rectified pair the matched depths
are the rendered ones; on a real KITTI 01 pair the disparities agree with an independent dense matcher (OpenCV's
semi-global block matching); bf comes from the dataset's pair and a frame without its right image is refused."""

from __future__ import annotations

import dataclasses
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pytest
from slamkit_orb.orbslam_extractor import OrbSlamExtractor

from slamkit.app import build_components
from slamkit.config import compose_config
from slamkit.errors import ConfigError, DatasetError
from slamkit.frontend.stereo import StereoFrontEnd, _sad_slide, image_pyramid, stereo_matches
from slamkit.interfaces import FrontEnd
from slamkit.plugins import ComponentRegistry

KITTI = Path("/work/shared/datasets/kitti")


def _built(*overrides: str, bind: bool = True) -> tuple[StereoFrontEnd, object]:
    registry = ComponentRegistry.discover()
    cfg = compose_config(["frontend=stereo", "dataset.max_frames=3", *overrides], registry=registry)
    components = build_components(cfg, registry)
    frontend = registry.instantiate("frontend", cfg.frontend, extractor=components["features"], init_extractor=None)
    assert isinstance(frontend, StereoFrontEnd) and isinstance(frontend, FrontEnd)
    if bind:
        frontend.bind_dataset(components["dataset"])
    return frontend, components["dataset"]


def test_synthetic_pair_gives_the_rendered_depths() -> None:
    frontend, dataset = _built("dataset.stereo=true")
    assert frontend.bf == pytest.approx(0.12 * dataset.camera.K[0, 0])  # type: ignore[attr-defined]
    data = dataset[0]  # type: ignore[index]
    obs = frontend.observe(data, dataset.camera)  # type: ignore[attr-defined]
    matched = np.isfinite(obs.depth_m)
    assert matched.sum() > 0.4 * len(obs)
    u, v = obs.uv_px[:, 0].astype(int), obs.uv_px[:, 1].astype(int)
    truth = data.depth_m[v, u][matched]
    rel = np.abs(obs.depth_m[matched] - truth) / truth
    assert np.median(rel) < 0.03 and np.mean(rel < 0.05) > 0.85
    np.testing.assert_allclose(
        obs.u_right_px[matched], obs.uv_px[matched, 0] - frontend.bf / obs.depth_m[matched], atol=1e-3
    )
    assert obs.sensor == "stereo" and obs.th_depth_m == pytest.approx(frontend.bf * 35.0 / dataset.camera.K[0, 0])  # type: ignore[attr-defined]


@pytest.mark.skipif(not (KITTI / "sequences" / "01").is_dir(), reason="KITTI 01 not in /work/shared")
def test_kitti_pair_disparities_agree_with_semi_global_matching() -> None:
    frontend, dataset = _built("dataset=kitti", f"dataset.root={KITTI}", "dataset.sequence=01", "dataset.stereo=true")
    assert frontend.bf == pytest.approx(386.1448, rel=1e-4)  # P1 of calib.txt: baseline 0.537 m x fx
    data = dataset[0]  # type: ignore[index]
    obs = frontend.observe(data, dataset.camera)  # type: ignore[attr-defined]
    matched = np.isfinite(obs.depth_m)
    assert matched.sum() > 600
    sgbm = cv2.StereoSGBM_create(0, 128, 5, P1=8 * 25, P2=32 * 25, uniquenessRatio=10)
    dense = sgbm.compute(data.image, data.image_right).astype(np.float32) / 16.0
    u, v = obs.uv_px[matched, 0].astype(int), obs.uv_px[matched, 1].ravel().astype(int)
    ref = dense[v, u]
    ours = (obs.uv_px[matched, 0] - obs.u_right_px[matched])[ref > 0]
    ref = ref[ref > 0]
    assert ref.size > 500
    assert np.median(np.abs(ours - ref)) < 1.0 and np.mean(np.abs(ours - ref) < 1.0) > 0.6
    assert np.median(ours / ref) == pytest.approx(1.0, abs=0.03)


def test_missing_right_image_or_baseline_is_refused() -> None:
    frontend, dataset = _built("dataset.stereo=true")
    data = dataset[1]  # type: ignore[index]
    with pytest.raises(DatasetError, match=r"frame 1 .*no right image"):
        frontend.observe(dataclasses.replace(data, image_right=None), dataset.camera)  # type: ignore[attr-defined]
    unbound, mono_dataset = _built(bind=False)  # the synthetic room without its right camera
    with pytest.raises(ConfigError, match="no stereo pair"):
        unbound.bind_dataset(mono_dataset)


def test_given_pyramids_and_split_matching_give_the_rebuilt_one_thread_matches() -> None:
    """``frontend.matching_pyramid=own``: the front end builds each image's matching pyramid in its extraction's thread
    and matches the odd keypoints in a second thread (issue 16, speed): the matches must be those of stereo_matches
    building its own pyramids in one thread, bit for bit, and the packed pyramid must hold ORB-SLAM's INTER_LINEAR
    levels (each from the one above)."""
    frontend, dataset = _built("dataset.stereo=true", "frontend.matching_pyramid=own")
    data = dataset[2]  # type: ignore[index]
    camera = dataset.camera  # type: ignore[attr-defined]
    extractor = frontend.extractor
    left, right = extractor.extract(data.image, camera), extractor.extract(data.image_right, camera)
    fx = float(camera.K[0, 0])
    assert frontend.bf is not None
    rebuilt = stereo_matches(left, right, data.image, data.image_right, frontend.bf, fx)
    pyramids = (
        image_pyramid(data.image, left.n_levels, left.scale_factor),
        image_pyramid(data.image_right, left.n_levels, left.scale_factor),
    )
    with ThreadPoolExecutor(max_workers=1) as pool:
        shared = stereo_matches(
            left, right, data.image, data.image_right, frontend.bf, fx, pyramids=pyramids, pool=pool
        )
    assert np.isfinite(rebuilt[1]).sum() > 0.4 * len(left)
    for a, b in zip(rebuilt, shared, strict=True):
        np.testing.assert_array_equal(a, b)  # NaN where unmatched on both sides
    # the front end's own observe gives the same record
    obs = frontend.observe(data, camera)
    np.testing.assert_array_equal(obs.u_right_px, rebuilt[0])
    np.testing.assert_array_equal(obs.depth_m, rebuilt[1])
    pixels, offsets, widths, heights = pyramids[0]
    level = data.image
    for lev in range(left.n_levels):
        if lev:
            level = cv2.resize(level, (int(widths[lev]), int(heights[lev])), interpolation=cv2.INTER_LINEAR)
        packed = pixels[offsets[lev] : offsets[lev] + widths[lev] * heights[lev]].reshape(heights[lev], widths[lev])
        np.testing.assert_array_equal(packed, level)


def test_default_matching_reads_the_extractors_pyramid() -> None:
    """The default (``matching_pyramid: extractor``, ORB-SLAM2's mvImagePyramid): each image is extracted alone in
    its thread, with the pyramid its keypoints were found on, and the SAD windows are read from those pyramids; the
    record is stereo_matches' on them, in one thread or split over two, and its depths are the rendered ones as with
    INTER_LINEAR levels (within a few hundredths of a pixel of disparity)."""
    frontend, dataset = _built("dataset.stereo=true")
    assert frontend.matching_pyramid == "extractor"
    data = dataset[2]  # type: ignore[index]
    camera = dataset.camera  # type: ignore[attr-defined]
    extractor = frontend.extractor
    assert isinstance(extractor, OrbSlamExtractor)
    left, pyr_l = extractor.extract_with_pyramid(data.image, camera)
    right, pyr_r = extractor.extract_with_pyramid(data.image_right, camera)
    fx = float(camera.K[0, 0])
    assert frontend.bf is not None
    ours = stereo_matches(
        left, right, data.image, data.image_right, frontend.bf, fx, pyramids=(pyr_l.packed(), pyr_r.packed())
    )
    with ThreadPoolExecutor(max_workers=1) as pool:
        split = stereo_matches(
            left,
            right,
            data.image,
            data.image_right,
            frontend.bf,
            fx,
            pyramids=(pyr_l.packed(), pyr_r.packed()),
            pool=pool,
        )
    obs = frontend.observe(data, camera)
    for a, b, c in zip(ours, split, (obs.u_right_px, obs.depth_m), strict=True):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, c)
    np.testing.assert_array_equal(obs.uv_px, left.uv_px)
    # against ORB-SLAM's INTER_LINEAR levels: nearly the same matches, sub-pixel positions within a few hundredths
    linear = stereo_matches(left, right, data.image, data.image_right, frontend.bf, fx)
    both = np.isfinite(ours[0]) & np.isfinite(linear[0])
    assert both.sum() > 0.97 * max(np.isfinite(ours[0]).sum(), np.isfinite(linear[0]).sum())
    du = np.abs(ours[0][both] - linear[0][both])
    assert np.median(du) < 0.05 and np.percentile(du, 95) < 0.5
    with pytest.raises(ConfigError, match="matching_pyramid"):
        StereoFrontEnd(extractor, matching_pyramid="linear")


@pytest.mark.parametrize(("w", "slide"), [(5, 5), (3, 2)])
def test_sad_slide_is_orbslams_window_sum(w: int, slide: int) -> None:
    """The compiled SAD slide (ComputeStereoMatches' 11 x 11 window minus its centre, slid +-5 px) against the sums
    written out with numpy, on random level images packed at an offset."""
    rng = np.random.default_rng(7)
    height, width, off = 40, 60, 123
    left = rng.integers(0, 256, (height, width), dtype=np.uint8)
    right = rng.integers(0, 256, (height, width), dtype=np.uint8)
    pad = rng.integers(0, 256, off, dtype=np.uint8)
    pyr_l = np.concatenate([pad, left.ravel()])
    pyr_r = np.concatenate([pad, right.ravel()])
    dists = np.zeros(2 * slide + 1, np.int32)
    for vl, ul, ur0 in ((w, w, w + slide), (20, 30, 25), (height - 1 - w, width - 1 - w, width - 1 - w - slide)):
        _sad_slide(pyr_l, pyr_r, off, width, vl, ul, ur0, w, slide, dists)
        wl = left[vl - w : vl + w + 1, ul - w : ul + w + 1].astype(np.int64) - int(left[vl, ul])
        for k in range(2 * slide + 1):
            ur = ur0 - slide + k
            wr = right[vl - w : vl + w + 1, ur - w : ur + w + 1].astype(np.int64) - int(right[vl, ur])
            assert dists[k] == np.abs(wl - wr).sum()


class _CountingExtractor:
    """The front end's extractor, noting OpenCV's thread count at each extraction (``extract_with_pyramid``)."""

    def __init__(self, inner: OrbSlamExtractor) -> None:
        self.inner = inner
        self.seen: list[int] = []

    def extract(self, image: np.ndarray, camera: object = None) -> object:
        return self.inner.extract(image, camera)  # type: ignore[arg-type]

    def extract_with_pyramid(self, image: np.ndarray, camera: object = None, threaded: bool = True) -> object:
        self.seen.append(cv2.getNumThreads())
        return self.inner.extract_with_pyramid(image, camera, threaded=threaded)  # type: ignore[arg-type]


def test_pair_opencv_threads_during_the_pair_only() -> None:
    """``pair_opencv_threads=1``: OpenCV's thread count is 1 while the two images are extracted in their two threads
    and the caller's count again afterwards; null (the default) leaves it alone; the record is the same."""
    frontend, dataset = _built("dataset.stereo=true", "frontend.pair_opencv_threads=1")
    assert frontend.pair_opencv_threads == 1
    assert _built("dataset.stereo=true")[0].pair_opencv_threads is None
    data = dataset[1]  # type: ignore[index]
    camera = dataset.camera  # type: ignore[attr-defined]
    inner = frontend.extractor
    assert isinstance(inner, OrbSlamExtractor)
    counting = _CountingExtractor(inner)
    frontend.extractor = frontend.right_extractor = counting  # type: ignore[assignment]
    before = cv2.getNumThreads()
    try:
        cv2.setNumThreads(3)
        ours = frontend.observe(data, camera)
        assert counting.seen == [1, 1] and cv2.getNumThreads() == 3
        frontend.pair_opencv_threads = None
        counting.seen.clear()
        theirs = frontend.observe(data, camera)
        assert counting.seen == [3, 3] and cv2.getNumThreads() == 3
    finally:
        cv2.setNumThreads(before)
    for a, b in ((ours.u_right_px, theirs.u_right_px), (ours.depth_m, theirs.depth_m), (ours.uv_px, theirs.uv_px)):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ConfigError, match="pair_opencv_threads"):
        StereoFrontEnd(inner, pair_opencv_threads=0)
