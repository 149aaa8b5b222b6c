"""keyframe_culling.table_rows (a lookup table over the point ids' range) against the binary search it replaced
(np.searchsorted's insertion rows): the same features found in the table at the same rows, and _count_redundant's
counts equal with either rows, on random tables that leave out ids, hold -1s and ids beyond both ends."""

from __future__ import annotations

import numpy as np
import pytest

from slamkit.pipeline.keyframe_culling import _count_redundant, table_rows


def _found(point_ids: np.ndarray, pids: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """The features whose row names their own id in the table (the kernel's test)."""
    P = point_ids.size
    if P == 0:
        return np.zeros(pids.size, bool)
    return (rows < P) & (point_ids[np.minimum(rows, P - 1)] == pids)


@pytest.mark.parametrize("seed", range(6))
def test_table_rows_find_the_rows_the_binary_search_found(seed: int) -> None:
    rng = np.random.default_rng(seed)
    point_ids = np.unique(rng.integers(5, 400, rng.integers(0, 120))).astype(np.int64)
    pids = rng.integers(-1, 420, 500).astype(np.int64)
    pids[::7] = -1
    rows = table_rows(point_ids, pids)
    want = np.searchsorted(point_ids, pids)
    found = _found(point_ids, pids, rows)
    assert np.array_equal(found, _found(point_ids, pids, want))
    assert np.array_equal(rows[found], want[found])
    assert np.all(rows[~found] == point_ids.size)  # the absent ones: row P, which the kernel skips
    if point_ids.size:
        assert found.any() and not found.all()


def test_table_rows_of_empty_inputs() -> None:
    assert table_rows(np.zeros(0, np.int64), np.array([-1, 3], np.int64)).tolist() == [0, 0]
    assert table_rows(np.array([2, 4], np.int64), np.zeros(0, np.int64)).size == 0


@pytest.mark.parametrize("seed", range(4))
def test_redundancy_counts_are_those_of_the_binary_search_rows(seed: int) -> None:
    """_count_redundant over random candidates, observations, culled observations and erased points."""
    rng = np.random.default_rng(seed)
    P, C, n_kf = 150, 6, 12
    point_ids = np.unique(rng.integers(0, 600, P)).astype(np.int64)
    P = point_ids.size
    counts = rng.integers(0, 7, P)
    ptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    E = int(ptr[-1])
    obs_kf = rng.integers(0, n_kf, E).astype(np.int64)
    obs_level = rng.integers(0, 8, E).astype(np.int64)
    alive = rng.random(E) > 0.1
    point_dead = rng.random(P) < 0.05
    feats = rng.integers(50, 120, C)
    cand_ptr = np.concatenate([[0], np.cumsum(feats)]).astype(np.int64)
    F = int(cand_ptr[-1])
    pids = np.where(rng.random(F) < 0.7, rng.choice(point_ids, F), rng.integers(-1, 700, F)).astype(np.int64)
    levels = rng.integers(0, 8, F).astype(np.int64)
    eligible = rng.random(F) > 0.1
    cand_kf = rng.permutation(n_kf)[:C].astype(np.int64)
    tail = (point_ids, ptr, obs_kf, obs_level, alive, point_dead, 2, 1)
    got = _count_redundant(cand_ptr, cand_kf, pids, levels, eligible, table_rows(point_ids, pids), *tail)
    want = _count_redundant(cand_ptr, cand_kf, pids, levels, eligible, np.searchsorted(point_ids, pids), *tail)
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
    assert got[0][1:].sum() > 0 and got[1][1:].sum() > 0  # the inputs exercise both counts
