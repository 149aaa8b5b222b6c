"""ORB-SLAM2's Tracking::UpdateLocalKeyFrames (V-D): K1 uncapped, K2 one neighbour, one child and the parent per K1
keyframe, growth stopped past 80 keyframes; and SearchByProjection's ratio test only between features of one level."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

from slamkit.pipeline.config import TrackingConfig
from slamkit.pipeline.matching import WindowMatches
from slamkit.pipeline.tracking.local_map import local_keyframes, points_seen_except


@dataclass
class _Point:
    observations: dict[int, int]


@dataclass
class _Tree:
    parents: dict[int, int]

    def parent(self, kf_id: int) -> int | None:
        return self.parents.get(kf_id)

    def children(self, kf_id: int) -> list[int]:
        return sorted(k for k, p in self.parents.items() if p == kf_id)


@dataclass
class _Covis:
    best: dict[int, list[int]]

    def best_neighbors(self, kf_id: int, n: int) -> list[int]:
        return self.best.get(kf_id, [])[:n]


@dataclass
class _Store:
    points: dict[int, _Point]
    keyframes: set[int]
    spanning_tree: _Tree
    covisibility: _Covis
    extra: dict[str, Any] = field(default_factory=dict)

    def get_point(self, pid: int) -> _Point:
        return self.points[pid]

    def has_keyframe(self, kf_id: int) -> bool:
        return kf_id in self.keyframes


class _Frame:
    def __init__(self, point_ids: list[int]) -> None:
        self.point_ids = np.array(point_ids, np.int64)


def test_k2_takes_one_new_neighbour_one_child_and_the_parent_of_each_k1_keyframe() -> None:
    # the frame sees points of keyframes 10 (two points) and 11 (one point)
    points = {0: _Point({10: 0}), 1: _Point({10: 1, 11: 0})}
    tree = _Tree({10: 5, 11: 10, 12: 10, 13: 10, 20: 11, 21: 11})
    covis = _Covis({10: [11, 12, 13, 14], 11: [10, 14, 15]})
    store = _Store(points, set(range(0, 30)), tree, covis)
    local, ref = local_keyframes(_Frame([0, 1, -1]), store, TrackingConfig())  # type: ignore[arg-type]
    assert ref == 10
    # K1 = [10, 11]; for 10: neighbour 12 (11 taken), child 13 (11, 12 taken), parent 5; for 11: neighbour 14,
    # child 20, parent 10 already in
    assert local == [10, 11, 12, 13, 5, 14, 20]


def test_k1_is_not_capped_and_k2_stops_past_the_cap() -> None:
    n = 100
    points = {i: _Point({i: 0}) for i in range(n)}
    tree = _Tree({i: i + 100 for i in range(n)})
    store = _Store(points, set(range(300)), tree, _Covis({}))
    local, _ = local_keyframes(_Frame(list(range(n))), store, TrackingConfig())  # type: ignore[arg-type]
    assert local == list(range(n))  # 100 K1 keyframes, none added: the set already holds more than 80
    cfg = TrackingConfig(local_map_covisible_keyframes=101)
    local, _ = local_keyframes(_Frame(list(range(n))), store, cfg)  # type: ignore[arg-type]
    assert local[n:] == [100, 101]  # parents added while the set held at most 101 keyframes


def test_local_map_ratio_test_applies_only_between_features_of_one_level() -> None:
    m = WindowMatches(
        best_index=np.array([3, 4, 5]),
        best_distance=np.array([40, 40, 40], np.int32),
        second_distance=np.array([45, 45, 60], np.int32),
        best_level=np.array([1, 1, 1], np.int32),
        second_level=np.array([1, 2, 1], np.int32),
    )
    # 40 >= 0.8 * 45: ambiguous on one level -> rejected; across levels ORB-SLAM keeps it
    assert m.accepted(100, 0.8, ratio_same_level_only=True).tolist() == [False, True, True]
    assert m.accepted(100, 0.8).tolist() == [False, False, True]


@pytest.mark.parametrize("seed", range(5))
def test_the_local_points_not_matched_yet_are_the_sorted_set_difference(seed: int) -> None:
    """points_seen_except: the local keyframes' distinct point ids (slots of -1 left out) not matched yet, ascending,
    exactly np.setdiff1d(np.unique(...)) — including matched ids beyond every local id and an empty result."""
    rng = np.random.default_rng(seed)
    ids = rng.integers(-1, 5000, size=int(rng.integers(0, 20000)))
    ids[rng.random(ids.size) < 0.3] = -1
    excluded = np.unique(rng.integers(0, 6000, size=int(rng.integers(0, 800))))
    got = points_seen_except(ids, excluded)
    want = np.setdiff1d(np.unique(ids[ids >= 0]), excluded, assume_unique=True)
    assert got.dtype == np.int64
    np.testing.assert_array_equal(got, want)
    everything = np.unique(ids[ids >= 0])
    assert points_seen_except(ids, everything).size == 0
    assert points_seen_except(np.full(4, -1, np.int64), excluded).size == 0
