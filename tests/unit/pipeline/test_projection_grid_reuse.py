"""match_projected's reused keyframe grid (fusion): the same matches as a grid built afresh, never another record's."""

from __future__ import annotations

import gc
import weakref
from typing import Any

import numpy as np

from slamkit.features import Features
from slamkit.pipeline import projection
from slamkit.pipeline.frame import ImageBounds
from slamkit.pipeline.projection import match_projected

BOUNDS = ImageBounds(0.0, 640.0, 0.0, 480.0)


def features(seed: int, n: int = 400) -> Features:
    rng = np.random.default_rng(seed)
    uv = rng.uniform([0, 0], [640, 480], size=(n, 2)).astype(np.float32)
    return Features(
        uv,
        uv.copy(),
        rng.integers(0, 3, n).astype(np.int32),
        rng.uniform(0, 360, n).astype(np.float32),
        np.ones(n, np.float32),
        rng.integers(0, 256, (n, 32)).astype(np.uint8),
        1.2,
        8,
    )


def queries(f: Features, seed: int) -> tuple[Any, ...]:
    """Projections near 3/8 of the keypoints with their descriptors a few bits off, and 50 random ones."""
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(f), 3 * len(f) // 8, replace=False)
    desc = f.descriptors[pick].copy()
    desc[:, 0] ^= rng.integers(0, 8, pick.size).astype(np.uint8)
    uv = f.uv_undist_px[pick].astype(np.float64) + rng.normal(0, 1.0, (pick.size, 2))
    uv = np.vstack([uv, rng.uniform([0, 0], [640, 480], (50, 2))])
    desc = np.vstack([desc, rng.integers(0, 256, (50, 32)).astype(np.uint8)])
    level = rng.integers(0, 3, uv.shape[0])
    return uv, desc, np.full(uv.shape[0], 4.0), level - 1, level


def match(f: Features, q: tuple[Any, ...], taken: np.ndarray, reuse: bool) -> tuple[np.ndarray, ...]:
    uv, desc, radius, min_level, max_level = q
    m = match_projected(
        f, taken, BOUNDS, uv, desc, radius, min_level, max_level, 50, None, None, None, reuse_grid=reuse
    )
    return m.query, m.feature, m.distance


def test_a_reused_grid_gives_the_matches_of_a_fresh_one() -> None:
    f = features(0)
    none = np.zeros(len(f), bool)
    for seed in range(3):  # the first call builds and keeps the grid, the others reuse it
        q = queries(f, seed)
        fresh, reused = match(f, q, none, False), match(f, q, none, True)
        assert fresh[0].size > 50
        for a, b in zip(fresh, reused, strict=True):
            np.testing.assert_array_equal(a, b)
    assert any(hit[0]() is f for hit in projection._FULL_GRIDS.values())
    taken = np.zeros(len(f), bool)
    taken[::2] = True  # something taken: never the kept grid
    q = queries(f, 5)
    for a, b in zip(match(f, q, taken, False), match(f, q, taken, True), strict=True):
        np.testing.assert_array_equal(a, b)
    assert not np.isin(match(f, q, taken, True)[1], np.flatnonzero(taken)).any()


def test_a_grid_is_never_handed_to_another_record() -> None:
    """A record that died leaves its entry under its id; a new record (which may get the same id) builds its own."""
    old = features(1)
    match(old, queries(old, 0), np.zeros(len(old), bool), True)
    ref = weakref.ref(old)
    key = next(k for k, hit in projection._FULL_GRIDS.items() if hit[0]() is old)
    del old
    gc.collect()
    assert ref() is None
    new = features(2)
    stale = projection._FULL_GRIDS[key]
    projection._FULL_GRIDS[(id(new), *key[1:])] = stale  # as if ``new`` had taken the dead record's id
    q = queries(new, 1)
    fresh = match(new, q, np.zeros(len(new), bool), False)
    for a, b in zip(fresh, match(new, q, np.zeros(len(new), bool), True), strict=True):
        np.testing.assert_array_equal(a, b)
    assert projection._FULL_GRIDS[(id(new), *key[1:])][0]() is new


def test_the_kept_grids_are_bounded() -> None:
    records = [features(10 + i, 50) for i in range(projection._FULL_GRIDS_MAX + 5)]
    for f in records:
        match(f, queries(f, 0), np.zeros(len(f), bool), True)
    assert len(projection._FULL_GRIDS) <= projection._FULL_GRIDS_MAX
