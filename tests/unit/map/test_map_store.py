"""Map store, covisibility graph, spanning tree, essential graph and the readers-writer lock."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from slamkit.errors import ConfigError
from slamkit.features import Features, Observations
from slamkit.geometry.camera import PinholeCamera
from slamkit.interfaces import MapStore
from slamkit.map.entities import KeyFrame, MapPoint
from slamkit.map.graphs import CovisibilityGraph, essential_graph_edges
from slamkit.map.lock import ReadWriteLock
from slamkit.map.store import InMemoryMapStore

CAMERA = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)


def _record(features: Features) -> Observations:
    """The monocular observation record of hand-made features (bearings through CAMERA)."""
    return Observations.monocular(features, CAMERA.unproject_image(features.uv_undist_px.astype(np.float64)))


def features(n: int) -> Observations:
    return _record(
        Features(
            uv_px=np.zeros((n, 2), np.float32),
            uv_undist_px=np.zeros((n, 2), np.float32),
            level=np.zeros(n, np.int32),
            angle_deg=np.zeros(n, np.float32),
            response=np.zeros(n, np.float32),
            descriptors=np.zeros((n, 32), np.uint8),
            scale_factor=1.2,
            n_levels=8,
        )
    )


def add_keyframe(store: InMemoryMapStore, n_features: int = 200) -> int:
    kf_id = store.new_keyframe_id()
    store.add_keyframe(
        KeyFrame(kf_id, kf_id, float(kf_id), np.eye(4), CAMERA, features(n_features), np.full(n_features, -1, np.int64))
    )
    return kf_id


def add_shared_points(store: InMemoryMapStore, kf_ids: list[int], count: int, start_feature: dict[int, int]) -> None:
    """Create ``count`` points seen by every keyframe in kf_ids (each keyframe's next free features)."""
    for _ in range(count):
        pid = store.new_point_id()
        store.add_point(MapPoint(pid, np.zeros(3), np.zeros(32, np.uint8), kf_ids[0], kf_ids[0]))
        for k in kf_ids:
            store.add_observation(pid, k, start_feature[k])
            start_feature[k] += 1


def test_store_satisfies_protocol_and_ids_are_monotonic() -> None:
    store = InMemoryMapStore()
    assert isinstance(store, MapStore)
    ids = [store.new_keyframe_id() for _ in range(3)]
    assert ids == [0, 1, 2]
    assert store.new_point_id() == 0 and store.new_point_id() == 1


def test_covisibility_threshold_spanning_tree_and_essential_graph() -> None:
    store = InMemoryMapStore(covisibility_min_shared=15)
    k = [add_keyframe(store) for _ in range(4)]
    nxt = dict.fromkeys(k, 0)
    add_shared_points(store, [k[0], k[1]], 120, nxt)  # strong edge 0-1
    add_shared_points(store, [k[1], k[2]], 20, nxt)  # weak but above 15
    add_shared_points(store, [k[2], k[3]], 10, nxt)  # below 15: kept only as k3's single best edge
    add_shared_points(store, [k[0], k[2]], 5, nxt)  # below 15, k2 has better: dropped
    for kf in k:
        store.update_connections(kf)
    cov = store.covisibility
    assert cov.weight(k[0], k[1]) == 120 and cov.weight(k[1], k[2]) == 20
    assert cov.weight(k[0], k[2]) == 0
    assert cov.weight(k[3], k[2]) == 10  # never isolated
    assert cov.neighbors(k[1]) == [k[0], k[2]]  # best first
    # spanning tree: parent = keyframe sharing the most points at insertion
    assert store.spanning_tree.parent(k[2]) == k[1] and store.spanning_tree.parent(k[3]) == k[2]
    store.add_loop_edge(k[3], k[0])

    def essential(theta_min: int) -> list[tuple[int, int]]:
        return essential_graph_edges(store.covisibility, store.spanning_tree, store.loop_edges(), theta_min)

    assert essential(100) == sorted(
        {tuple(sorted(e)) for e in store.spanning_tree.edges()} | {(k[0], k[1]), (k[0], k[3])}
    )
    # lowering theta_min adds the weaker covisibility edges
    assert (k[1], k[2]) in essential(15)
    assert len(essential(15)) >= len(essential(100))


def test_removing_a_keyframe_reparents_children_and_drops_orphan_points() -> None:
    store = InMemoryMapStore()
    k = [add_keyframe(store) for _ in range(3)]
    nxt = dict.fromkeys(k, 0)
    add_shared_points(store, [k[0], k[1]], 50, nxt)
    add_shared_points(store, [k[1], k[2]], 50, nxt)
    add_shared_points(store, [k[0], k[2]], 30, nxt)
    add_shared_points(store, [k[1]], 7, nxt)  # seen only by k1
    for kf in k:
        store.update_connections(kf)
    assert store.spanning_tree.parent(k[2]) == k[1]
    n_points = store.n_points()
    store.remove_keyframe(k[1])
    assert not store.has_keyframe(k[1]) and k[1] not in store.covisibility
    assert store.n_points() == n_points - 7  # points seen only by k1 are gone
    assert store.spanning_tree.parent(k[2]) == k[0]  # re-attached to the best remaining candidate
    for pid in store.point_ids():
        assert k[1] not in store.get_point(pid).observations


def test_removing_a_point_clears_keyframe_references() -> None:
    store = InMemoryMapStore()
    k = [add_keyframe(store) for _ in range(2)]
    nxt = dict.fromkeys(k, 0)
    add_shared_points(store, k, 1, nxt)
    store.remove_point(0)
    assert all(store.get_keyframe(kf).n_tracked_points() == 0 for kf in k)


def test_covisibility_ties_are_deterministic() -> None:
    g = CovisibilityGraph()
    g.update_connections(5, {3: 20, 1: 20, 2: 30}, 15)
    assert g.neighbors(5) == [2, 1, 3]


def test_writer_excludes_readers_and_is_not_starved() -> None:
    lock = ReadWriteLock()
    events: list[str] = []
    reader_in = threading.Event()

    def long_reader() -> None:
        with lock.read():
            reader_in.set()
            time.sleep(0.05)
            events.append("reader1 done")

    def writer() -> None:
        with lock.write():
            events.append("writer")

    def late_reader() -> None:
        with lock.read():
            events.append("reader2")

    t1 = threading.Thread(target=long_reader)
    t1.start()
    reader_in.wait()
    t2 = threading.Thread(target=writer)
    t2.start()
    time.sleep(0.01)  # the writer is now waiting
    t3 = threading.Thread(target=late_reader)
    t3.start()
    for t in (t1, t2, t3):
        t.join(timeout=5)
    assert events == ["reader1 done", "writer", "reader2"]


def test_bad_config_is_named() -> None:
    with pytest.raises(ConfigError, match=r"map\.covisibility_min_shared"):
        InMemoryMapStore(covisibility_min_shared=0)


def test_a_nested_read_does_not_wait_for_a_waiting_writer_and_the_writer_waits_for_the_outer_read() -> None:
    """Tracking holds the read lock for a whole frame and its steps take it again: a writer (a merge's move) that
    starts waiting in between must neither deadlock the nested read nor get in before the outer read ends."""
    lock = ReadWriteLock()
    events: list[str] = []
    outer_in, writer_waiting = threading.Event(), threading.Event()

    def tracking() -> None:
        with lock.read():
            outer_in.set()
            writer_waiting.wait(5)
            time.sleep(0.02)  # the writer is waiting now
            with lock.read():
                events.append("nested read")
            events.append("outer read done")

    def writer() -> None:
        writer_waiting.set()
        with lock.write():
            events.append("writer")

    t1 = threading.Thread(target=tracking, daemon=True)  # daemon: a deadlock fails the test, not the run
    t1.start()
    outer_in.wait(5)
    t2 = threading.Thread(target=writer, daemon=True)
    t2.start()
    for t in (t1, t2):
        t.join(timeout=5)
    assert not t1.is_alive() and not t2.is_alive()
    assert events == ["nested read", "outer read done", "writer"]


def test_reader_waiting_goes_in_between_a_writers_back_to_back_writes() -> None:
    """Local mapping writes in a series of short phases; tracking's read must not wait for the whole series."""
    lock = ReadWriteLock()
    events: list[str] = []
    writer_in = threading.Event()

    def writer() -> None:
        for i in range(20):
            with lock.write():
                events.append(f"w{i}")
                writer_in.set()
                time.sleep(0.002)

    def reader() -> None:
        with lock.read():
            events.append("r")

    t1 = threading.Thread(target=writer)
    t1.start()
    writer_in.wait(timeout=5)
    t2 = threading.Thread(target=reader)
    t2.start()
    for t in (t1, t2):
        t.join(timeout=5)
    assert not t1.is_alive() and not t2.is_alive()
    # the reader arrived during write phase 0 (or 1): it is let in right after that phase
    assert events.index("r") <= 3, events
