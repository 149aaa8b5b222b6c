"""The point table mirrors the map points: every change the store makes reaches it, and nothing else can change a
point (entities are read-only outside their store)."""

from __future__ import annotations

import copy
import pickle
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from slamkit.app import build_runner
from slamkit.config import compose_config
from slamkit.features import Features, Observations
from slamkit.geometry.camera import PinholeCamera
from slamkit.map.entities import KeyFrame, MapPoint
from slamkit.map.store import InMemoryMapStore


def _point(store: InMemoryMapStore, seed: int) -> MapPoint:
    rng = np.random.default_rng(seed)
    return MapPoint(
        store.new_point_id(), rng.normal(size=3), rng.integers(0, 256, 32).astype(np.uint8), 0, 0, d_min_m=0.5
    )


def test_assignments_through_the_store_reach_the_table_and_the_points() -> None:
    store = InMemoryMapStore()
    points = [_point(store, i) for i in range(3)]
    for p in points:
        store.add_point(p)
    ids = np.array([p.id for p in points])
    np.testing.assert_array_equal(store.point_rows(ids, "xyz_w"), [p.xyz_w for p in points])
    store.assign_points(ids[1:2], "xyz_w", np.array([[1.0, 2.0, 3.0]]))
    store.assign_points(ids[2:], "descriptor", np.full((1, 32), 7, np.uint8))
    store.assign_points(ids[:1], "normal_w", np.array([[0.0, 0.0, 1.0]]))
    store.assign_points(ids[:1], "d_max_m", np.array([9.5]))
    np.testing.assert_array_equal(store.point_rows(ids[1:2], "xyz_w"), [[1.0, 2.0, 3.0]])
    np.testing.assert_array_equal(points[1].xyz_w, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(store.point_rows(ids[2:], "descriptor"), [np.full(32, 7, np.uint8)])
    np.testing.assert_array_equal(store.point_rows(ids[:1], "normal_w"), [[0.0, 0.0, 1.0]])
    np.testing.assert_array_equal(store.point_rows(ids, "d_max_m"), [9.5, np.inf, np.inf])
    assert points[0].d_max_m == 9.5 and isinstance(points[0].d_max_m, float)
    np.testing.assert_array_equal(store.point_rows(ids, "d_min_m"), [0.5, 0.5, 0.5])


def test_a_point_cannot_be_changed_behind_the_store() -> None:
    store = InMemoryMapStore()
    p = _point(store, 0)
    store.add_point(p)
    before = store.point_rows(np.array([p.id]), "xyz_w")
    with pytest.raises(ValueError, match="read-only"):
        p.xyz_w[0] = 5.0  # the in-place write the old write-through mirror silently missed
    with pytest.raises(AttributeError):
        p.xyz_w = np.zeros(3)  # type: ignore[misc]
    with pytest.raises(TypeError):
        p.observations[0] = 1  # type: ignore[index]
    np.testing.assert_array_equal(store.point_rows(np.array([p.id]), "xyz_w"), before)


def test_rows_survive_the_table_growing_and_removed_points_are_let_go() -> None:
    store = InMemoryMapStore()
    first = _point(store, 0)
    store.add_point(first)
    for i in range(1, 5000):  # past the initial capacity: the arrays are reallocated
        store.add_point(_point(store, i))
    np.testing.assert_array_equal(store.point_rows(np.array([first.id]), "xyz_w"), [first.xyz_w])
    store.remove_point(first.id)
    np.testing.assert_array_equal(store.has_points(np.array([-1, first.id, 1, 4999, 5000])), [0, 0, 1, 1, 0])
    with pytest.raises(ValueError, match="not reused"):
        store.add_point(first)


def test_copies_of_a_point_belong_to_no_store() -> None:
    store = InMemoryMapStore()
    k = store.new_keyframe_id()
    uv, zeros = np.zeros((4, 2), np.float32), np.zeros(4, np.float32)
    camera = PinholeCamera(64, 48, 50.0, 50.0, 32.0, 24.0)
    feats = Features(uv, uv, np.zeros(4, np.int32), zeros, zeros, np.zeros((4, 32), np.uint8), 1.2, 8)
    record = Observations.monocular(feats, camera.unproject_image(uv.astype(np.float64)))
    store.add_keyframe(KeyFrame(k, 0, 0.0, np.eye(4), camera, record, np.full(4, -1)))
    p = _point(store, 0)
    store.add_point(p)
    store.add_observation(p.id, k, 2)
    for clone in (copy.deepcopy(p), pickle.loads(pickle.dumps(p))):
        assert clone.id == p.id and np.array_equal(clone.xyz_w, p.xyz_w) and dict(clone.observations) == {k: 2}
        with pytest.raises(ValueError, match="read-only"):
            clone.xyz_w[0] = 4.0
    store.remove_observation(p.id, k)  # the copies keep the observations they were made with
    assert not store.has_point(p.id) and dict(clone.observations) == {k: 2}


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
        compose_config(["runner=threaded", "runner.progress=false", "dataset.max_frames=70", "dataset.depth=false"])
    )
    runner.run(dataset, dataset.camera)
    assert runner.store.n_points() > 300
    assert_point_table_matches_points(runner.store)
