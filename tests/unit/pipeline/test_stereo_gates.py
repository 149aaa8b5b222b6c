"""The stereo/RGB-D candidate gates of ORB-SLAM2's ORBmatcher in the window search: SearchByProjection's right-
coordinate check and Fuse's 3-dof reprojection chi-square, against a brute-force reference; a gated candidate is
neither best nor second best (the gate sits before the descriptor comparison, as in ORB-SLAM2)."""

from __future__ import annotations

import numpy as np
import pytest

from slamkit.pipeline.matching import (
    GATE_REPROJECTION_CHI2,
    GATE_RIGHT_U,
    FeatureGrid,
    RightGate,
    search_windows,
)
from slamkit.pipeline.projection import predicted_u_right


def brute_hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.unpackbits(a[:, None, :] ^ b[None, :, :], axis=2).sum(axis=2)


def test_right_u_gate_skips_a_wrong_depth_in_favour_of_the_next_candidate() -> None:
    """Two candidates at the projection: the better descriptor has a right coordinate 9 px off the predicted one
    (a keypoint whose depth belongs to another surface), the worse one agrees. With the gate (tolerance 4 px) the
    match is the agreeing one and the rejected candidate does not count as second best; without it, the wrong one."""
    rng = np.random.default_rng(7)
    q_desc = rng.integers(0, 256, (1, 32), dtype=np.uint8)
    t_desc = np.repeat(q_desc, 2, axis=0)
    t_desc[1, :4] ^= 0xFF  # 32 bits away: the worse descriptor
    grid = FeatureGrid.build(np.array([[200.0, 100.0], [202.0, 101.0]]), np.zeros(2, np.int32), 640, 480)
    query = np.array([[201.0, 100.0]])
    plain = search_windows(grid, t_desc, query, q_desc, 5.0)
    assert plain.best_index[0] == 0 and plain.second_distance[0] == 32
    gate = RightGate(GATE_RIGHT_U, np.array([150.0]), np.array([159.0, 151.0]), tolerance_px=np.array([4.0]))
    gated = search_windows(grid, t_desc, query, q_desc, 5.0, right_gate=gate)
    assert gated.best_index[0] == 1 and gated.best_distance[0] == 32
    assert gated.second_distance[0] == 1 << 30, "the rejected candidate is not a second best either"
    # a candidate without a right coordinate (NaN: a monocular observation of the keypoint) is not gated
    mono = RightGate(GATE_RIGHT_U, np.array([150.0]), np.array([np.nan, 151.0]), tolerance_px=np.array([4.0]))
    assert search_windows(grid, t_desc, query, q_desc, 5.0, right_gate=mono).best_index[0] == 0


def test_fuse_gate_equals_brute_force_chi2() -> None:
    """Fuse's in-window check: (du^2 + dv^2 + du_R^2) / sigma^2 <= 7.8 where the candidate has a right coordinate,
    (du^2 + dv^2) / sigma^2 <= 5.99 where it has none; the best surviving descriptor per query."""
    rng = np.random.default_rng(8)
    n_train, n_query = 4000, 400
    t_uv = rng.uniform([0, 0], [640, 480], (n_train, 2))
    t_level = rng.integers(0, 8, n_train).astype(np.int32)
    t_desc = rng.integers(0, 256, (n_train, 32), dtype=np.uint8)
    t_ur = t_uv[:, 0] - rng.uniform(2.0, 30.0, n_train)
    t_ur[rng.random(n_train) < 0.3] = np.nan
    inv_s2 = 1.0 / np.power(1.2, 2.0 * t_level)
    q_uv = rng.uniform([0, 0], [640, 480], (n_query, 2))
    q_desc = rng.integers(0, 256, (n_query, 32), dtype=np.uint8)
    q_z = rng.uniform(0.5, 5.0, n_query)
    q_ur = predicted_u_right(q_uv, q_z, 40.0)
    radius = np.full(n_query, 12.0)
    grid = FeatureGrid.build(t_uv, t_level, 640, 480, cell_px=16.0)
    gate = RightGate(GATE_REPROJECTION_CHI2, q_ur, t_ur, train_inv_sigma2=inv_s2, chi2_mono=5.99, chi2_stereo=7.8)
    got = search_windows(grid, t_desc, q_uv, q_desc, radius, right_gate=gate)
    dist = brute_hamming(q_desc, t_desc)
    e2 = np.sum((q_uv[:, None] - t_uv[None]) ** 2, axis=2)
    er2 = (q_ur[:, None] - t_ur[None]) ** 2
    stereo = np.isfinite(t_ur)[None]
    passes = np.where(stereo, (e2 + np.nan_to_num(er2)) * inv_s2[None] <= 7.8, e2 * inv_s2[None] <= 5.99)
    allowed = (e2 <= radius[:, None] ** 2) & passes
    n_checked = 0
    for i in range(n_query):
        cand = np.flatnonzero(allowed[i])
        if cand.size == 0:
            assert got.best_index[i] == -1
            continue
        n_checked += 1
        assert got.best_distance[i] == dist[i, cand].min() and got.best_index[i] in cand
    assert n_checked > 20


def test_gate_arguments_are_checked() -> None:
    grid = FeatureGrid.build(np.array([[10.0, 10.0]]), np.zeros(1, np.int32), 64, 48)
    desc = np.zeros((1, 32), np.uint8)
    with pytest.raises(ValueError, match="tolerance_px"):
        search_windows(
            grid,
            desc,
            np.array([[10.0, 10.0]]),
            desc,
            3.0,
            right_gate=RightGate(GATE_RIGHT_U, np.zeros(1), np.zeros(1)),
        )
