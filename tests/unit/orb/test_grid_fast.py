"""Grid FAST: one low-threshold run with per-cell selection equals ORB-SLAM's per-cell two-threshold runs."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray
from slamkit_orb.grid_fast import GridFast
from slamkit_orb.patterns import textured_image, uneven_texture_image
from slamkit_orb.pyramid import build_pyramid, level_sizes


def _fast(image: NDArray[np.uint8], threshold: int) -> dict[tuple[int, int], float]:
    detector = cv2.FastFeatureDetector.create(threshold=threshold, nonmaxSuppression=True)
    return {(round(k.pt[0]), round(k.pt[1])): k.response for k in detector.detect(image)}


def _orbslam_cells(image: NDArray[np.uint8], edge: int = 19, cell: float = 30.0) -> set[tuple[int, int]]:
    """ORB-SLAM's ComputeKeyPointsOctTree corner collection, cell by cell (FAST 20, else FAST 7)."""
    min_b, max_bx, max_by = edge - 3, image.shape[1] - edge + 3, image.shape[0] - edge + 3
    width, height = max_bx - min_b, max_by - min_b
    n_cols, n_rows = int(width / cell), int(height / cell)
    w_cell, h_cell = math.ceil(width / n_cols), math.ceil(height / n_rows)
    found: set[tuple[int, int]] = set()
    for i in range(n_rows):
        y0 = min_b + i * h_cell
        if y0 >= max_by - 3:
            continue
        y1 = min(y0 + h_cell + 6, max_by)
        for j in range(n_cols):
            x0 = min_b + j * w_cell
            if x0 >= max_bx - 6:
                continue
            x1 = min(x0 + w_cell + 6, max_bx)
            corners = _fast(image[y0:y1, x0:x1], 20) or _fast(image[y0:y1, x0:x1], 7)
            found |= {(x + x0, y + y0) for x, y in corners}
    return found


def _images() -> list[NDArray[np.uint8]]:
    return [textured_image(seed=1), uneven_texture_image(seed=2)]


@pytest.mark.parametrize("index", [0, 1])
def test_high_threshold_corners_are_the_low_threshold_run_filtered_by_score(index: int) -> None:
    image = _images()[index]
    strong = _fast(image, 20)
    weak = _fast(image, 7)
    assert len(weak) > len(strong) > 100
    assert strong == {xy: r for xy, r in weak.items() if r >= 20}


def test_score_equivalence_holds_on_a_real_image(tum_image: NDArray[np.uint8]) -> None:
    strong = _fast(tum_image, 20)
    assert strong == {xy: r for xy, r in _fast(tum_image, 7).items() if r >= 20}


@pytest.mark.parametrize("index", [0, 1])
def test_grid_selection_matches_orbslams_per_cell_runs(index: int) -> None:
    image = _images()[index]
    corners = GridFast(19, 30, 20, 7).detect(image)
    ours = {(int(x), int(y)) for x, y in corners.xy}
    reference = _orbslam_cells(image)
    # The only difference is non-maximum suppression across cell borders (see grid_fast.py): ORB-SLAM's
    # per-cell runs keep a corner next to a stronger one just across a cell border, the single run does not.
    # Cells start at x = 19 + 31 j and y = 19 + 32 i for a 640x480 level.
    only_reference = np.array(sorted(reference - ours))
    near_x = np.minimum((only_reference[:, 0] - 19) % 31, 31 - (only_reference[:, 0] - 19) % 31) <= 1
    near_y = np.minimum((only_reference[:, 1] - 19) % 32, 32 - (only_reference[:, 1] - 19) % 32) <= 1
    assert np.all(near_x | near_y)
    # Rarely a cell whose only strong corner was suppressed that way falls back to its weak corners.
    assert len(ours - reference) <= 0.01 * len(ours)
    assert len(ours & reference) >= 0.85 * len(reference)


def test_fallback_threshold_finds_corners_in_low_contrast_cells() -> None:
    image = uneven_texture_image(seed=4)  # weak part: contrast <= 14 grey levels, right of x = 192 px
    with_fallback = GridFast(19, 30, 20, 7).detect(image)
    without = GridFast(19, 30, 20, 20).detect(image)
    weak_part = with_fallback.xy[:, 0] > 200
    assert np.count_nonzero(weak_part) > 100
    assert np.all(with_fallback.response[weak_part] < 20)
    assert np.count_nonzero(without.xy[:, 0] > 200) == 0
    # In the strong part, cells with strong corners keep only those.
    strong_part = with_fallback.xy[:, 0] < 150
    assert np.all(with_fallback.response[strong_part & (with_fallback.xy[:, 1] < 100)] >= 20)


def test_corners_stay_inside_the_edge_threshold() -> None:
    image = textured_image(seed=5)
    corners = GridFast(19, 30, 20, 7).detect(image)
    x, y = corners.xy[:, 0], corners.xy[:, 1]
    assert x.min() >= 19 and y.min() >= 19
    assert x.max() < 640 - 19 and y.max() < 480 - 19
    assert corners.region == (16, 16, 624, 464)


@pytest.mark.parametrize("shape", [(10, 10), (44, 300), (300, 44), (45, 45)])
def test_levels_too_small_for_detection_give_no_corners(shape: tuple[int, int]) -> None:
    image = np.random.default_rng(0).integers(0, 256, size=shape, dtype=np.uint8)
    corners = GridFast(19, 30, 20, 7).detect(image)
    if min(shape) <= 2 * 19:
        assert corners.xy.shape == (0, 2)
    else:
        assert corners.xy.shape[0] > 0  # a 45x45 level still has a 7x7 detection area


def _dense_frame() -> NDArray[np.uint8]:
    synthetic = pytest.importorskip("slamkit.io.synthetic")
    return np.asarray(synthetic.SyntheticDataset(scene="room", depth=False, imu=False, max_frames=1)[0].image)


@pytest.mark.parametrize("source", ["shapes", "uneven", "noise", "synthetic"])
def test_both_fast_strategies_give_identical_corners(source: str) -> None:
    """'cells' (FAST 20 everywhere, FAST 7 only on weak cells widened by 4 px) == 'whole' (FAST 7 everywhere),
    bit for bit and in the same order, on every pyramid level."""
    image = {
        "shapes": lambda: textured_image(seed=6),
        "uneven": lambda: uneven_texture_image(seed=7),
        "noise": lambda: np.random.default_rng(8).integers(0, 256, size=(480, 640), dtype=np.uint8),
        "synthetic": _dense_frame,
    }[source]()
    most_weak = _assert_strategies_agree(image)
    assert most_weak > 0.0 or source == "noise"


def test_both_fast_strategies_agree_on_real_images(
    tum_image: NDArray[np.uint8], euroc_image: NDArray[np.uint8], kitti_image: NDArray[np.uint8]
) -> None:
    for image in (tum_image, euroc_image, kitti_image):
        assert _assert_strategies_agree(image) > 0.2  # many weak cells re-run at the low threshold


def _assert_strategies_agree(image: NDArray[np.uint8]) -> float:
    """Checks every level; returns the largest share of weak cells seen (cells the 'cells' path re-ran)."""
    grid = GridFast(19, 30, 20, 7)
    h, w = image.shape
    most_weak = 0.0
    for level_image in build_pyramid(image, level_sizes(w, h, 1.2, 8)):
        whole = grid.detect(level_image, "whole")
        cells = grid.detect(level_image, "cells")
        np.testing.assert_array_equal(cells.xy, whole.xy)
        np.testing.assert_array_equal(cells.response, whole.response)
        assert cells.weak_share == pytest.approx(whole.weak_share)
        most_weak = max(most_weak, cells.weak_share)
    return most_weak
