"""Fusion's compiled helpers and its gathers agree with the numpy expressions they replace."""

from __future__ import annotations

import numpy as np
import pytest

from slamkit.pipeline.fusion import absent_from
from slamkit.pipeline.map_points import unique_point_ids


@pytest.mark.parametrize("seed", range(5))
def test_absent_from_is_not_in_the_own_points(seed: int) -> None:
    rng = np.random.default_rng(seed)
    own = np.where(rng.random(300) < 0.4, rng.integers(0, 5_000, 300), -1)
    ids = rng.integers(-2, 6_000, 400)
    got = absent_from(ids, own)
    np.testing.assert_array_equal(got, ~np.isin(ids, own[own >= 0]))
    assert got.any() and not got.all()


def test_absent_from_without_own_points_keeps_every_id() -> None:
    ids = np.arange(10, dtype=np.int64)
    assert absent_from(ids, np.full(5, -1, np.int64)).all()
    assert absent_from(np.zeros(0, np.int64), np.arange(3, dtype=np.int64)).shape == (0,)
    read_only = np.arange(3, dtype=np.int64)
    read_only.setflags(write=False)  # a keyframe's point_ids view
    np.testing.assert_array_equal(absent_from(ids, read_only), ids >= 3)


@pytest.mark.parametrize("seed", range(3))
def test_unique_point_ids_is_numpy_unique_of_the_ids(seed: int) -> None:
    rng = np.random.default_rng(seed)
    parts = [np.where(rng.random(200) < 0.5, rng.integers(0, 3_000, 200), -1) for _ in range(6)]
    expected = np.unique(np.concatenate(parts))
    got = unique_point_ids(parts)
    assert got.dtype == np.int64
    np.testing.assert_array_equal(got, expected[expected >= 0])
    assert unique_point_ids([]).size == 0 and unique_point_ids([np.full(4, -1, np.int64)]).size == 0
