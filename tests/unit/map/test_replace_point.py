"""MapStore.replace_point (ORB-SLAM MapPoint::Replace) in the in-memory store: the survivor takes every observation
of the replaced point by a keyframe it is not seen by, in keyframe-id order, and its counters stay the sums they
are by definition (observations; ORB-SLAM's weighted count, 2 for a keypoint with a right coordinate)."""

from __future__ import annotations

import numpy as np
import pytest

from slamkit.map.entities import observation_weight
from slamkit.map.store import InMemoryMapStore
from tests.unit.pipeline.test_map_point_refresh import random_map


def check_counters(store: InMemoryMapStore) -> None:
    pids = np.array(store.point_ids(), np.int64)
    points = store.get_points(pids.tolist())
    assert store.point_rows(pids, "n_observations").tolist() == [len(p.observations) for p in points]
    weighted = [
        sum(observation_weight(store.get_keyframe(k).features, f) for k, f in p.observations.items()) for p in points
    ]
    assert store.point_rows(pids, "n_observations_orbslam").tolist() == weighted
    for kf_id in store.keyframe_ids():
        own = store.get_keyframe(kf_id).point_ids
        for f in np.flatnonzero(own >= 0).tolist():
            assert store.get_point(int(own[f])).observations[kf_id] == f


@pytest.mark.parametrize("rgbd", [False, True])
def test_replace_point_moves_the_observations_and_keeps_the_counts(rgbd: bool) -> None:
    store = random_map(4, n_kf=8, n_points=200, rgbd=rgbd)
    rng = np.random.default_rng(4)
    pids = store.point_ids()
    for _ in range(40):
        old, new = (int(p) for p in rng.choice(pids, 2, replace=False))
        if not (store.has_point(old) and store.has_point(new)):
            continue
        old_obs = dict(store.get_point(old).observations)
        new_obs = dict(store.get_point(new).observations)
        store.replace_point(old, new)
        assert not store.has_point(old)
        moved = {k: f for k, f in sorted(old_obs.items()) if k not in new_obs}
        assert list(store.get_point(new).observations.items()) == [*new_obs.items(), *moved.items()]
        for k, f in old_obs.items():
            if k not in moved:  # seen by new at another keypoint: old's keypoint is left without a point
                assert store.get_keyframe(k).point_ids[f] == -1
    check_counters(store)
