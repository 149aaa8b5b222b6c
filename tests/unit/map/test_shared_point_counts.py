"""The in-memory store's shared-point counts (covisibility weights, ORB-SLAM KeyFrame::UpdateConnections) are the
per-point loop's, keys in the same first-seen order (the covisibility graph keeps them in that order)."""

from __future__ import annotations

import numpy as np
import pytest

from slamkit.map.store import InMemoryMapStore
from tests.unit.pipeline.test_map_point_refresh import random_map


def loop_counts(store: InMemoryMapStore, kf_id: int) -> dict[int, int]:
    """Other keyframe -> points it shares with kf_id, walking kf_id's points and each point's observers."""
    counts: dict[int, int] = {}
    for pid in store.get_keyframe(kf_id).point_ids.tolist():
        if pid < 0 or not store.has_point(pid):
            continue
        for other in store.get_point(pid).observations:
            if other != kf_id:
                counts[other] = counts.get(other, 0) + 1
    return counts


@pytest.mark.parametrize("seed", range(3))
def test_shared_point_counts_are_the_loops_in_its_order(seed: int) -> None:
    store = random_map(seed, n_kf=8, n_points=300)
    rng = np.random.default_rng(seed)
    for pid in rng.choice(store.point_ids(), 40, replace=False).tolist():  # their keypoints become -1
        store.remove_point(pid)
    for kf_id in store.keyframe_ids():
        got = store.shared_point_counts(kf_id)
        want = loop_counts(store, kf_id)
        assert list(got.items()) == list(want.items())
        assert kf_id not in got and sum(got.values()) > 0
