"""The point table mirrors the map points' geometry: every assignment of a point in the map reaches it."""

from __future__ import annotations

import copy
import pickle
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from slamkit.app import build_runner
from slamkit.config import compose_config
from slamkit.map.entities import MapPoint
from slamkit.map.store import InMemoryMapStore


def _point(store: InMemoryMapStore, seed: int) -> MapPoint:
    rng = np.random.default_rng(seed)
    return MapPoint(
        store.new_point_id(), rng.normal(size=3), rng.integers(0, 256, 32).astype(np.uint8), 0, 0, d_min_m=0.5
    )


def test_assignments_of_points_in_the_map_reach_the_table() -> None:
    store = InMemoryMapStore()
    points = [_point(store, i) for i in range(3)]
    for p in points:
        store.add_point(p)
    ids = np.array([p.id for p in points])
    np.testing.assert_array_equal(store.point_rows(ids, "xyz_w"), [p.xyz_w for p in points])
    points[1].xyz_w = np.array([1.0, 2.0, 3.0])
    points[2].descriptor = np.full(32, 7, np.uint8)
    points[0].normal_w = np.array([0.0, 0.0, 1.0])
    points[0].d_max_m = 9.5
    np.testing.assert_array_equal(store.point_rows(ids[1:2], "xyz_w"), [[1.0, 2.0, 3.0]])
    np.testing.assert_array_equal(store.point_rows(ids[2:], "descriptor"), [np.full(32, 7, np.uint8)])
    np.testing.assert_array_equal(store.point_rows(ids[:1], "normal_w"), [[0.0, 0.0, 1.0]])
    np.testing.assert_array_equal(store.point_rows(ids, "d_max_m"), [9.5, np.inf, np.inf])
    np.testing.assert_array_equal(store.point_rows(ids, "d_min_m"), [0.5, 0.5, 0.5])


def test_rows_survive_the_table_growing_and_removed_points_are_let_go() -> None:
    store = InMemoryMapStore()
    first = _point(store, 0)
    store.add_point(first)
    for i in range(1, 5000):  # past the initial capacity: the arrays are reallocated
        store.add_point(_point(store, i))
    np.testing.assert_array_equal(store.point_rows(np.array([first.id]), "xyz_w"), [first.xyz_w])
    store.remove_point(first.id)
    first.xyz_w = np.zeros(3)  # no longer in the map: nothing to mirror, and no error
    assert "_table" not in first.__dict__


def test_copies_of_a_point_belong_to_no_store() -> None:
    store = InMemoryMapStore()
    p = _point(store, 0)
    store.add_point(p)
    for clone in (copy.deepcopy(p), pickle.loads(pickle.dumps(p))):
        assert clone.id == p.id and np.array_equal(clone.xyz_w, p.xyz_w) and "_table" not in clone.__dict__
        clone.xyz_w = np.full(3, 4.0)
    np.testing.assert_array_equal(store.point_rows(np.array([p.id]), "xyz_w"), [p.xyz_w])


def test_a_descriptor_of_another_width_is_refused_with_the_point_named() -> None:
    store = InMemoryMapStore()
    store.add_point(_point(store, 0))
    odd = MapPoint(store.new_point_id(), np.zeros(3), np.zeros(61, np.uint8), 0, 0)
    with pytest.raises(ValueError, match=r"map point 1: descriptor of shape \(61,\).*\(32,\)"):
        store.add_point(odd)


@pytest.mark.timeout(300)
def test_after_a_threaded_run_the_table_equals_the_points(
    assert_point_table_matches_points: Callable[[Any], None],
) -> None:
    runner, dataset = build_runner(
        compose_config(["runner=threaded", "runner.progress=false", "dataset.max_frames=200", "dataset.depth=false"])
    )
    runner.run(dataset, dataset.camera)
    assert runner.store.n_points() > 500
    assert_point_table_matches_points(runner.store)
