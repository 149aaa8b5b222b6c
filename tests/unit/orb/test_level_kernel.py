"""The compiled level kernel gives exactly what the Python path gives: GridFast's "whole" selection, the quadtree
and the orientation, level by level; and the extractor's output does not depend on the FAST backend."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray
from slamkit_orb.grid_fast import GridFast
from slamkit_orb.level_kernel import level_keypoints, levels_keypoints
from slamkit_orb.orbslam_extractor import OrbSlamExtractor
from slamkit_orb.orientation import circular_patch_extent
from slamkit_orb.pyramid import build_pyramid, features_per_level, level_sizes

U8 = NDArray[np.uint8]
U_MAX = circular_patch_extent(15)


def _room_frames() -> list[U8]:
    from slamkit.io.synthetic import SyntheticDataset

    dataset = SyntheticDataset(scene="room", depth=False, imu=False)
    return [np.asarray(dataset[i].image, np.uint8) for i in (0, 400)]


def _low_contrast(seed: int) -> U8:
    """Mostly flat with faint blobs: many weak cells, so the fallback threshold matters."""
    rng = np.random.default_rng(seed)
    image = np.full((480, 640), 120, np.uint8)
    for _ in range(60):
        x, y, r = int(rng.integers(20, 620)), int(rng.integers(20, 460)), int(rng.integers(3, 12))
        cv2.circle(image, (x, y), r, int(rng.choice([108, 132, 160])), -1)
    return image


@pytest.mark.parametrize("n_features", [1000, 100])
def test_every_level_equals_the_python_path(n_features: int) -> None:
    """Against the extractor's step-by-step path (GridFast, quadtree, orientation: its opencv-backend code)."""
    grid = GridFast(19, 30, 20, 7)
    stepwise = OrbSlamExtractor(n_features=n_features, fast_backend="opencv", n_threads=1)
    for image in [*_room_frames(), _low_contrast(3)]:
        h, w = image.shape
        for level, level_image in enumerate(build_pyramid(image, level_sizes(w, h, 1.2, 8))):
            budget = int(stepwise.level_budget[level])
            xy, response, angle, _ = level_keypoints(grid, level_image, budget, U_MAX)
            want = stepwise._level(level, level_image)
            if want is None:
                assert xy.shape[0] == 0
                continue
            np.testing.assert_array_equal(xy, want.xy)
            np.testing.assert_array_equal(response, want.response)
            np.testing.assert_array_equal(angle, want.angle_deg)
            assert xy.shape[0] <= budget


def test_weak_share_is_the_grids() -> None:
    grid = GridFast(19, 30, 20, 7)
    for image in [_room_frames()[0], _low_contrast(3)]:
        assert level_keypoints(grid, image, 500, U_MAX)[3] == grid.detect(image, "whole").weak_share


def test_a_group_of_levels_in_one_call_equals_level_by_level() -> None:
    grid = GridFast(19, 30, 20, 7)
    image = _room_frames()[1]
    levels = build_pyramid(image, level_sizes(640, 480, 1.2, 8))
    budgets = features_per_level(1000, 1.2, 8)
    chosen = [0, 3, 4, 7]
    tiny = np.zeros((12, 12), np.uint8)  # too small for FAST: a level with nothing
    xy, response, angle, counts, weak = levels_keypoints(
        grid, [levels[k] for k in chosen] + [tiny], [int(budgets[k]) for k in chosen] + [5], U_MAX
    )
    each = [level_keypoints(grid, levels[k], int(budgets[k]), U_MAX) for k in chosen]
    np.testing.assert_array_equal(counts, [e[0].shape[0] for e in each] + [0])
    np.testing.assert_array_equal(xy, np.concatenate([e[0] for e in each]))
    np.testing.assert_array_equal(response, np.concatenate([e[1] for e in each]))
    np.testing.assert_array_equal(angle, np.concatenate([e[2] for e in each]))
    np.testing.assert_array_equal(weak, [e[3] for e in each] + [1.0])


@pytest.mark.parametrize("shape", [(40, 40), (10, 300), (480, 640)])
def test_small_and_blank_levels_give_nothing(shape: tuple[int, int]) -> None:
    xy, response, angle, weak = level_keypoints(GridFast(19, 30, 20, 7), np.zeros(shape, np.uint8), 100, U_MAX)
    assert xy.shape == (0, 2) and response.size == 0 and angle.size == 0 and weak == 1.0


@pytest.mark.parametrize("n_threads", [1, 2, 3])
def test_extractor_output_does_not_depend_on_the_fast_backend(shared_datasets: Path, n_threads: int) -> None:
    kitti = cv2.imread(str(shared_datasets / "kitti" / "sequences" / "07" / "image_0" / "000000.png"), 0)
    for image, n in [(_room_frames()[1], 1000), (np.asarray(kitti, np.uint8), 2000), (_low_contrast(5), 1000)]:
        a = OrbSlamExtractor(n_features=n, fast_backend="compiled", n_threads=n_threads).extract(image)
        b = OrbSlamExtractor(n_features=n, fast_backend="opencv", n_threads=1).extract(image)
        assert len(a) > 0
        for field in ("uv_px", "level", "angle_deg", "response", "descriptors"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)
