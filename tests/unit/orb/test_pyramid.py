"""The scale pyramid and ORB-SLAM's split of the feature budget over its levels."""

from __future__ import annotations

import numpy as np
import pytest
from slamkit_orb.patterns import textured_image
from slamkit_orb.pyramid import build_packed_pyramid, build_pyramid, features_per_level, level_scales, level_sizes


def test_budget_split_is_orbslams_geometric_series() -> None:
    budget = features_per_level(1000, 1.2, 8)
    # ORB-SLAM's numbers for its default settings: 1000 * (1 - 1/1.2) / (1 - 1.2^-8) = 217.3 at level 0.
    assert budget.tolist() == [217, 181, 151, 126, 105, 87, 73, 60]
    assert budget.sum() == 1000


@pytest.mark.parametrize(("n", "scale", "levels"), [(1000, 1.2, 8), (2000, 1.2, 8), (1500, 1.2, 8), (500, 1.5, 4)])
def test_budget_follows_the_series_and_sums_to_n_features(n: int, scale: float, levels: int) -> None:
    budget = features_per_level(n, scale, levels)
    first = n * (1 - 1 / scale) / (1 - scale**-levels)
    series = first * scale ** -np.arange(levels)
    assert budget.sum() == n
    # Every level but the last is the rounded term; the last absorbs the rounding (at most a few features).
    assert np.all(np.abs(budget[:-1] - series[:-1]) <= 0.5 + 1e-9)
    assert abs(budget[-1] - series[-1]) <= levels * 0.5
    assert np.all(np.diff(budget) <= 0)


def test_single_level_gets_everything() -> None:
    assert features_per_level(1000, 1.2, 1).tolist() == [1000]


def test_level_sizes_match_opencvs_rounding() -> None:
    sizes = level_sizes(640, 480, 1.2, 8)
    assert sizes == [
        (640, 480),
        (533, 400),
        (444, 333),
        (370, 278),
        (309, 231),
        (257, 193),
        (214, 161),
        (179, 134),
    ]
    np.testing.assert_allclose(level_scales(1.2, 8), 1.2 ** np.arange(8), rtol=1e-6)


def test_pyramid_levels_have_the_level_sizes() -> None:
    image = textured_image(seed=3)
    sizes = level_sizes(640, 480, 1.2, 8)
    pyramid = build_pyramid(image, sizes)
    assert [(p.shape[1], p.shape[0]) for p in pyramid] == sizes
    assert pyramid[0] is image
    # Each level is a smoothed copy of the previous one: its mean grey level is kept within a grey level.
    assert all(abs(float(p.mean()) - float(image.mean())) < 1.0 for p in pyramid)


def test_pyramid_stops_at_an_empty_level() -> None:
    sizes = level_sizes(1, 1, 1.2, 8)
    assert sizes[4] == (0, 0)  # 1 / 1.2^4 = 0.48 rounds to 0
    pyramid = build_pyramid(np.zeros((1, 1), np.uint8), sizes)
    assert [p.shape for p in pyramid] == [(1, 1)] * 4


@pytest.mark.parametrize(("width", "height"), [(640, 480), (1241, 376), (1, 1)])
def test_packed_pyramid_holds_the_pyramids_levels(width: int, height: int) -> None:
    """build_packed_pyramid: the same pixels as build_pyramid, each level at its offset in one array, and one
    zero-sized entry per level past the first empty one."""
    image = textured_image(seed=5, width=width, height=height) if width > 1 else np.full((1, 1), 7, np.uint8)
    sizes = level_sizes(width, height, 1.2, 8)
    levels = build_pyramid(image, sizes)
    packed = build_packed_pyramid(image, sizes)
    assert len(packed.levels) == len(levels)
    assert packed.pixels.size == sum(level.size for level in levels)
    for k, (ours, theirs) in enumerate(zip(packed.levels, levels, strict=True)):
        np.testing.assert_array_equal(ours, theirs)
        start = int(packed.offsets[k])
        np.testing.assert_array_equal(packed.pixels[start : start + ours.size], theirs.ravel())
    assert packed.widths.tolist() == [w for w, _ in sizes[: len(levels)]] + [0] * (8 - len(levels))
    assert packed.heights.tolist() == [h for _, h in sizes[: len(levels)]] + [0] * (8 - len(levels))
