"""Matching primitives against brute-force references."""

from __future__ import annotations

import numpy as np
import pytest

from slamkit.pipeline.matching import (
    FeatureGrid,
    hamming_matrix,
    hamming_rows,
    resolve_one_to_one,
    rotation_consistent,
    search_windows,
)


def brute_hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.unpackbits(a[:, None, :] ^ b[None, :, :], axis=2).sum(axis=2)


def test_hamming_matrix_and_rows_match_bit_counting() -> None:
    rng = np.random.default_rng(1)
    a = rng.integers(0, 256, (57, 32), dtype=np.uint8)
    b = rng.integers(0, 256, (43, 32), dtype=np.uint8)
    ref = brute_hamming(a, b)
    np.testing.assert_array_equal(hamming_matrix(a, b), ref)
    np.testing.assert_array_equal(hamming_rows(a[:43], b), ref[np.arange(43), np.arange(43)])
    assert hamming_matrix(a, a).diagonal().max() == 0


def test_search_windows_equals_brute_force_with_radius_and_levels() -> None:
    rng = np.random.default_rng(2)
    n_train, n_query = 800, 300
    t_uv = rng.uniform([0, 0], [640, 480], (n_train, 2))
    t_level = rng.integers(0, 8, n_train).astype(np.int32)
    t_desc = rng.integers(0, 256, (n_train, 32), dtype=np.uint8)
    q_uv = rng.uniform([-20, -20], [660, 500], (n_query, 2))
    q_desc = rng.integers(0, 256, (n_query, 32), dtype=np.uint8)
    radius = rng.uniform(5, 60, n_query)
    lo = rng.integers(0, 4, n_query)
    hi = lo + rng.integers(0, 4, n_query)
    grid = FeatureGrid.build(t_uv, t_level, 640, 480, cell_px=16.0)
    got = search_windows(grid, t_desc, q_uv, q_desc, radius, lo, hi)
    dist = brute_hamming(q_desc, t_desc)
    inside = (np.linalg.norm(q_uv[:, None] - t_uv[None], axis=2) <= radius[:, None]) & (
        (t_level[None] >= lo[:, None]) & (t_level[None] <= hi[:, None])
    )
    for i in range(n_query):
        cand = np.flatnonzero(inside[i])
        if cand.size == 0:
            assert got.best_index[i] == -1
            continue
        d = np.sort(dist[i, cand])
        assert got.best_distance[i] == d[0]
        assert dist[i, got.best_index[i]] == d[0] and got.best_index[i] in cand
        if cand.size > 1:
            assert got.second_distance[i] == d[1]


def test_accepted_applies_threshold_and_ratio() -> None:
    rng = np.random.default_rng(3)
    t_desc = rng.integers(0, 256, (2, 32), dtype=np.uint8)
    q_desc = t_desc.copy()
    q_desc[1] = t_desc[0]  # query 1 sits on train 1's position but looks like train 0
    grid = FeatureGrid.build(np.array([[100.0, 100.0], [300.0, 300.0]]), np.zeros(2, np.int32), 640, 480)
    m = search_windows(grid, t_desc, np.array([[101.0, 100.0], [300.0, 301.0]]), q_desc, 5.0)
    assert list(m.best_index) == [0, 1] and m.best_distance[0] == 0
    assert list(m.accepted(max_distance=50, ratio=0.9)) == [True, False]


def test_one_to_one_keeps_the_closest_claim() -> None:
    q = np.array([0, 1, 2, 3])
    t = np.array([5, 5, 6, 5])
    d = np.array([40, 10, 30, 10])
    assert list(resolve_one_to_one(q, t, d)) == [False, True, True, False]


def test_rotation_consistency_rejects_odd_orientations() -> None:
    rng = np.random.default_rng(4)
    good = rng.normal(20.0, 2.0, 200)  # the image rotated by ~20 deg
    bad = np.array([150.0, 250.0, 300.0])
    keep = rotation_consistent(np.concatenate([good, bad]), 30)
    assert keep[:200].mean() > 0.95 and not keep[200:].any()


def _numpy_grid(uv: np.ndarray, width: int, height: int, cell_px: float) -> tuple[np.ndarray, ...]:
    """The grid's arrays as NumPy computes them (the reference the compiled counting sort must equal bit for bit)."""
    n_cols, n_rows = max(1, int(np.ceil(width / cell_px))), max(1, int(np.ceil(height / cell_px)))
    with np.errstate(invalid="ignore"):  # +-1e300 // cell_px: out of int64, as in the compiled cast
        col = np.clip((uv[:, 0] // cell_px).astype(np.int64), 0, n_cols - 1)
        row = np.clip((uv[:, 1] // cell_px).astype(np.int64), 0, n_rows - 1)
    cell = row * n_cols + col
    counts = np.bincount(cell, minlength=n_rows * n_cols)
    end = np.cumsum(counts)
    return np.argsort(cell, kind="stable"), end - counts, end


def test_feature_grid_cells_and_order_equal_numpys_floor_division_and_stable_sort() -> None:
    """Cells from float floor division (values on and next to cell borders, outside the image, negative) and the
    order within a cell by feature index, as ``np.argsort(kind="stable")`` gives."""
    rng = np.random.default_rng(4)
    border = np.array([0.0, -0.0, 10.0, np.nextafter(10.0, 0.0), np.nextafter(10.0, 20.0), 0.3 * 100, 29.999999999999996,
                       np.nextafter(640.0, 0.0), 640.0, 700.0, -5.0, -1e-300, 1e300, -1e300])  # fmt: skip
    for trial in range(60):
        n = int(rng.integers(0, 2500))
        uv = rng.uniform(-20.0, 660.0, (n, 2)) if trial % 2 else rng.choice(border, (n, 2))
        cell_px = float(rng.choice([10.0, 3.0, 7.3, 0.1 * 3]))
        grid = FeatureGrid.build(uv, np.zeros(n, np.int32), 640, 480, cell_px)
        order, start, end = _numpy_grid(uv, 640, 480, cell_px)
        np.testing.assert_array_equal(grid.order, order)
        np.testing.assert_array_equal(grid.cell_start, start)
        np.testing.assert_array_equal(grid.cell_end, end)
        assert grid.order.dtype == grid.cell_start.dtype == grid.cell_end.dtype == np.int64


@pytest.mark.parametrize("seed", range(4))
def test_rotation_consistent_keeps_the_three_fullest_bins_as_the_isin_rule(seed: int) -> None:
    """The bin lookup keeps what ``np.isin(bins, keep_bins)`` keeps (ComputeThreeMaxima), ties and NaN-free angles
    in [-720, 720) deg."""
    rng = np.random.default_rng(seed)
    diff = np.concatenate([rng.normal(10.0, 3.0, 60), rng.normal(200.0, 5.0, 12), rng.uniform(-720, 720, 40)])
    bins = (np.mod(diff, 360.0) * (30 / 360.0)).astype(np.int64) % 30
    counts = np.bincount(bins, minlength=30)
    ranked = np.argsort(-counts, kind="stable")
    keep_bins = [ranked[0]] + [b for b in ranked[1:3] if counts[b] > 0.1 * counts[ranked[0]]]
    got = rotation_consistent(diff, 30)
    np.testing.assert_array_equal(got, np.isin(bins, keep_bins))
    assert got.dtype == bool and got.any() and not got.all()
