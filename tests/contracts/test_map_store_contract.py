"""The MapStore contract: every registered map store (first-party or third-party) must pass these tests.

Parametrized over ``ComponentRegistry.discover().components("map")`` plus the example third-party store of
tests/plugins/slamkit_dictmap (``map=dict``, pip-installed for this module), each built from its default config
node through the registry (which checks it against slamkit.map.protocol.MapStore). What is held to: the behaviour
documented in slamkit/map/protocol.py, on small maps whose right answer the test counts itself.
"""

from __future__ import annotations

import copy
import dataclasses
import pickle
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from slamkit.errors import PluginError
from slamkit.features import Features, Observations
from slamkit.geometry.camera import PinholeCamera
from slamkit.interfaces import BowDescription, MapStore
from slamkit.map.entities import KeyFrame, MapPoint
from slamkit.map.ids import IdAllocator
from slamkit.map.mapfile_contents import differences, read_map_contents
from slamkit.plugins import ComponentRegistry

NAMES = sorted({c.spec.name for c in ComponentRegistry.discover().components("map")} | {"dict"})
CAMERA = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)
N_FEATS = 200
GEOMETRY = ("xyz_w", "normal_w", "d_min_m", "d_max_m", "descriptor")

StoreFactory = Callable[..., MapStore]


@pytest.fixture(scope="module")
def registry(dictmap_plugin: Path) -> ComponentRegistry:
    return ComponentRegistry.discover()


@pytest.fixture(params=NAMES)
def make_store(request: pytest.FixtureRequest, registry: ComponentRegistry) -> StoreFactory:
    """make_store(**kwargs) -> a new store of the parametrized kind (kwargs: runtime arguments such as ids)."""
    node = registry.get("map", request.param).config_node()

    def make(**kwargs: Any) -> MapStore:
        store = registry.instantiate("map", node, **kwargs)
        assert isinstance(store, MapStore)
        return store

    return make


@pytest.fixture
def store(make_store: StoreFactory) -> MapStore:
    return make_store()


def features(n: int = N_FEATS, seed: int = 0) -> Observations:
    """The monocular observation record of n random keypoints."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform(0, 480, (n, 2)).astype(np.float32)
    feats = Features(
        uv,
        uv,
        rng.integers(0, 8, n).astype(np.int32),
        np.zeros(n, np.float32),
        np.ones(n, np.float32),
        rng.integers(0, 256, (n, 32), dtype=np.uint8),
        1.2,
        8,
    )
    return Observations.monocular(feats, CAMERA.unproject_image(uv.astype(np.float64)))


def add_keyframe(store: MapStore, x_m: float = 0.0, point_ids: np.ndarray | None = None) -> int:
    kf_id = store.new_keyframe_id()
    T = np.eye(4)
    T[0, 3] = -x_m
    matched = np.full(N_FEATS, -1, np.int64) if point_ids is None else point_ids
    store.add_keyframe(KeyFrame(kf_id, kf_id, float(kf_id), T, CAMERA, features(seed=kf_id), matched))
    return kf_id


def add_point(store: MapStore, observers: dict[int, int], seed: int = 0) -> int:
    """A point at a random place in front of the cameras, observed by keyframe -> feature ``observers``."""
    rng = np.random.default_rng(seed)
    pid = store.new_point_id()
    first = min(observers) if observers else 0
    xyz = rng.uniform([-1, -1, 3], [1, 1, 6])
    store.add_point(MapPoint(pid, xyz, rng.integers(0, 256, 32).astype(np.uint8), first, first))
    for kf_id, feat in observers.items():
        store.add_observation(pid, kf_id, feat)
    return pid


class FreeFeatures:
    """Next free feature of each keyframe (the tests' bookkeeping)."""

    def __init__(self) -> None:
        self.next: dict[int, int] = {}

    def take(self, kf_id: int) -> int:
        self.next[kf_id] = self.next.get(kf_id, 0) + 1
        return self.next[kf_id] - 1


def shared(store: MapStore, kf_ids: list[int], count: int, free: FreeFeatures, seed: int = 0) -> list[int]:
    """``count`` points seen by every keyframe of kf_ids."""
    return [add_point(store, {k: free.take(k) for k in kf_ids}, seed + i) for i in range(count)]


def assert_consistent(
    store: MapStore, visible: dict[int, int] | None = None, found: dict[int, int] | None = None
) -> None:
    """Observations both ways; point_rows equal the entities (and the counters the test's own count)."""
    pids = store.point_ids()
    for kf_id in store.keyframe_ids():
        kf = store.get_keyframe(kf_id)
        for feat in np.flatnonzero(kf.point_ids >= 0).tolist():
            pid = int(kf.point_ids[feat])
            assert store.has_point(pid), (kf_id, feat, pid)
            assert store.get_point(pid).observations[kf_id] == feat
    for pid in pids:
        point = store.get_point(pid)
        assert point.observations, pid
        for kf_id, feat in point.observations.items():
            assert store.get_keyframe(kf_id).point_ids[feat] == pid
    if not pids:
        return
    ids = np.array(pids, np.int64)
    for name in GEOMETRY:
        rows = store.point_rows(ids, name)
        np.testing.assert_array_equal(rows, np.array([getattr(store.get_point(p), name) for p in pids]), name)
    np.testing.assert_array_equal(
        store.point_rows(ids, "n_observations"), [len(store.get_point(p).observations) for p in pids]
    )
    weighted = [
        sum(
            2 if np.isfinite(store.get_keyframe(k).features.u_right_px[i]) else 1
            for k, i in store.get_point(p).observations.items()
        )
        for p in pids
    ]
    np.testing.assert_array_equal(store.point_rows(ids, "n_observations_orbslam"), weighted)
    if visible is not None and found is not None:
        np.testing.assert_array_equal(store.point_rows(ids, "n_visible"), [visible[p] for p in pids])
        np.testing.assert_array_equal(store.point_rows(ids, "n_found"), [found[p] for p in pids])


# ---- ids ----------------------------------------------------------------------------------------------------


def test_ids_are_monotonic_and_never_reused(store: MapStore) -> None:
    kfs = [add_keyframe(store) for _ in range(3)]
    assert kfs == sorted(kfs) and len(set(kfs)) == 3
    free = FreeFeatures()
    pids = shared(store, kfs[:2], 3, free)
    assert pids == sorted(pids) and len(set(pids)) == 3
    kept = store.get_keyframe(kfs[2])
    store.remove_keyframe(kfs[2])
    with pytest.raises(ValueError):
        store.add_keyframe(kept)  # an erased keyframe's id is not used again
    point = store.get_point(pids[0])
    store.remove_point(pids[0])
    with pytest.raises(ValueError):
        store.add_point(MapPoint(point.id, point.xyz_w, point.descriptor, kfs[0], kfs[0]))
    with pytest.raises(ValueError):  # an id the store's allocator never issued
        store.add_point(MapPoint(10_000, np.zeros(3), np.zeros(32, np.uint8), kfs[0], kfs[0]))
    assert store.new_keyframe_id() > max(kfs) and store.new_point_id() > max(pids)


def test_stores_sharing_an_allocator_never_hand_out_the_same_id(make_store: StoreFactory) -> None:
    ids = IdAllocator()
    a, b = make_store(ids=ids), make_store(ids=ids)
    assert a.ids is ids and b.ids is ids
    kf_ids = [add_keyframe(s) for s in (a, b, a, b, b)]
    assert kf_ids == sorted(set(kf_ids))
    free = FreeFeatures()
    point_ids = [add_point(s, {s.keyframe_ids()[0]: free.take(s.keyframe_ids()[0])}) for s in (b, a, b)]
    assert point_ids == sorted(set(point_ids))
    assert a.keyframe_ids() == [kf_ids[0], kf_ids[2]] and b.keyframe_ids() == [kf_ids[1], kf_ids[3], kf_ids[4]]
    assert a.point_ids() == [point_ids[1]]


# ---- observations and culling ----------------------------------------------------------------------------------


def test_observations_are_recorded_both_ways(store: MapStore) -> None:
    k0, k1, k2 = (add_keyframe(store, x) for x in (0.0, 0.2, 0.4))
    pid = add_point(store, {k0: 5, k1: 7, k2: 9})
    assert dict(store.get_point(pid).observations) == {k0: 5, k1: 7, k2: 9}
    assert [store.get_keyframe(k).point_ids[f] for k, f in ((k0, 5), (k1, 7), (k2, 9))] == [pid] * 3
    assert store.point_rows(np.array([pid]), "n_observations")[0] == 3
    store.remove_observation(pid, k0)  # the reference keyframe goes: the smallest remaining observer takes over
    assert dict(store.get_point(pid).observations) == {k1: 7, k2: 9}
    assert store.get_keyframe(k0).point_ids[5] == -1 and store.get_point(pid).ref_kf_id == k1
    store.remove_observation(pid, k2)  # fewer than two observations: the point is erased (EraseObservation)
    assert not store.has_point(pid) and store.get_keyframe(k1).point_ids[7] == -1
    assert_consistent(store)


def add_rgbd_keyframe(store: MapStore, with_right: np.ndarray) -> int:
    """A keyframe whose keypoints ``with_right`` (N_FEATS,) bool have a depth and a right coordinate (RGB-D)."""
    kf_id = store.new_keyframe_id()
    obs = features(seed=kf_id)
    depth = np.where(with_right, 2.0, np.nan).astype(np.float32)
    obs = dataclasses.replace(obs, depth_m=depth, u_right_px=obs.uv_px[:, 0] - 40.0 / depth, bf=40.0, sensor="rgbd")
    store.add_keyframe(KeyFrame(kf_id, kf_id, float(kf_id), np.eye(4), CAMERA, obs, np.full(N_FEATS, -1, np.int64)))
    return kf_id


def test_orbslam_observation_counter_weighs_stereo_observations_twice(store: MapStore) -> None:
    """The counter "n_observations_orbslam" is ORB-SLAM's MapPoint::Observations(): 2 per observation at a keypoint with a right
    coordinate, 1 otherwise, through adding, moving and removing observations, replacing points and keyframes."""
    right = np.arange(N_FEATS) % 2 == 0  # even keypoints have a depth
    a, b, c = (add_rgbd_keyframe(store, right) for _ in range(3))
    p = add_point(store, {a: 0, b: 1, c: 2})  # 2 + 1 + 2
    q = add_point(store, {a: 3, b: 4}, seed=1)  # 1 + 2
    r = add_point(store, {a: 5, b: 7, c: 9}, seed=2)  # 1 + 1 + 1

    def counts() -> list[int]:
        ids = [pid for pid in (p, q, r) if store.has_point(pid)]
        return store.point_rows(np.array(ids, np.int64), "n_observations_orbslam").tolist()

    assert counts() == [5, 3, 3]
    assert_consistent(store)
    store.add_observation(r, c, 8)  # keyframe c now sees r at an even keypoint: 1 + 1 + 2
    assert counts() == [5, 3, 4]
    store.remove_observation(p, b)  # 2 + 2
    assert counts() == [4, 3, 4]
    store.replace_point(q, r)  # r gains nothing new from a and b (it has them), q goes
    assert not store.has_point(q) and counts() == [4, 4]
    store.remove_keyframe(c)  # p: 2 (a), r: 1 + 1
    assert_consistent(store)


def test_adding_a_keyframe_keeps_the_tracked_points_still_in_the_map(store: MapStore) -> None:
    k0, k1 = add_keyframe(store), add_keyframe(store, 0.2)
    free = FreeFeatures()
    a, b, c = shared(store, [k0, k1], 3, free)
    store.remove_point(c)
    tracked = np.full(N_FEATS, -1, np.int64)
    tracked[[3, 4, 10, 11]] = [a, c, b, a]  # c is gone; a is matched twice: the first feature keeps it
    k2 = add_keyframe(store, 0.4, tracked)
    kf = store.get_keyframe(k2)
    assert kf.point_ids[[3, 4, 10, 11]].tolist() == [a, -1, b, -1]
    assert store.get_point(a).observations[k2] == 3 and store.get_point(b).observations[k2] == 10
    assert_consistent(store)


def test_removing_a_point_clears_every_keyframe_entry(store: MapStore) -> None:
    kfs = [add_keyframe(store, x) for x in (0.0, 0.2, 0.4)]
    pid = add_point(store, {kfs[0]: 1, kfs[1]: 2, kfs[2]: 3})
    store.remove_point(pid)
    assert not store.has_point(pid) and pid not in store.point_ids()
    assert all(store.get_keyframe(k).n_tracked_points() == 0 for k in kfs)
    assert not store.has_points(np.array([pid, -1]))[0:2].any()


def test_removing_a_keyframe_reparents_its_children_and_erases_orphan_points(store: MapStore) -> None:
    k: list[int] = []
    free = FreeFeatures()
    # keyframes arrive one by one, each sharing points with earlier ones, as local mapping inserts them
    for others, counts in (([], []), ([0], [50]), ([1, 0], [50, 30]), ([1, 2], [40, 20])):
        k.append(add_keyframe(store, 0.1 * len(k)))
        for o, count in zip(others, counts, strict=True):
            shared(store, [k[o], k[-1]], count, free)
        store.update_connections(k[-1])
    only_k1 = [add_point(store, {k[1]: free.take(k[1])}) for _ in range(7)]
    tree = store.spanning_tree
    assert [tree.parent(kf) for kf in k] == [None, k[0], k[1], k[1]]
    assert tree.children(k[1]) == [k[2], k[3]]
    store.add_loop_edge(k[3], k[1])
    n_points = store.n_points()
    store.remove_keyframe(k[1])
    assert not store.has_keyframe(k[1]) and k[1] not in store.covisibility and k[1] not in tree
    assert store.n_points() == n_points - 7 and not store.has_points(np.array(only_k1)).any()
    # ORB-SLAM SetBadFlag: the children go to the best-connected candidate, starting from the parent k0
    assert tree.parent(k[2]) == k[0] and tree.parent(k[3]) == k[2]
    assert sorted(tree.children(k[0])) == [k[2]] and tree.children(k[2]) == [k[3]]
    assert store.loop_edges() == []
    for pid in store.point_ids():
        assert k[1] not in store.get_point(pid).observations
    assert_consistent(store)


# ---- graphs --------------------------------------------------------------------------------------------------


def test_covisibility_weights_are_shared_points_above_the_threshold(store: MapStore) -> None:
    k = [add_keyframe(store, 0.1 * i) for i in range(4)]
    free = FreeFeatures()
    store.update_connections(k[0])  # the first keyframe, alone: the root of the spanning tree
    shared(store, [k[0], k[1]], 30, free)
    store.update_connections(k[1])
    shared(store, [k[0], k[1], k[2]], 20, free)  # a point seen by three keyframes counts for each pair
    store.update_connections(k[2])
    shared(store, [k[2], k[3]], 10, free)  # below 15: kept only as k3's single best edge
    shared(store, [k[0], k[3]], 4, free)  # below 15 and not the best of either: no edge
    store.update_connections(k[3])
    for kf in k:
        store.update_connections(kf)
    cov = store.covisibility
    assert cov.weight(k[0], k[1]) == 50 and cov.weight(k[1], k[0]) == 50
    assert cov.weight(k[0], k[2]) == 20 and cov.weight(k[1], k[2]) == 20
    assert cov.weight(k[2], k[3]) == 10 and cov.weight(k[0], k[3]) == 0
    assert cov.neighbors(k[0]) == [k[1], k[2]] and cov.neighbors(k[2]) == [k[0], k[1], k[3]]  # ties: lower id
    assert cov.neighbors(k[2], min_weight=15) == [k[0], k[1]] and cov.best_neighbors(k[2], 1) == [k[0]]
    assert cov.edges() == [(k[0], k[1], 50), (k[0], k[2], 20), (k[1], k[2], 20), (k[2], k[3], 10)]
    assert store.spanning_tree.edges() == [(k[0], k[1]), (k[0], k[2]), (k[2], k[3])]
    assert store.spanning_tree.parent(k[0]) is None and store.spanning_tree.children(k[0]) == [k[1], k[2]]
    store.add_loop_edge(k[3], k[0])
    store.add_loop_edge(k[0], k[3])
    assert store.loop_edges() == [(k[0], k[3])]


def assert_tree_has_no_cycle(store: MapStore) -> None:
    """Following parents from any keyframe ends at a root within as many steps as there are keyframes."""
    tree = store.spanning_tree
    for kf_id in store.keyframe_ids():
        seen = [kf_id]
        parent = tree.parent(kf_id)
        while parent is not None:
            assert parent not in seen, f"a cycle in the spanning tree: {[*seen, parent]}"
            seen.append(parent)
            parent = tree.parent(parent)


@pytest.mark.parametrize("shared_allocator", [False, True], ids=["own-ids", "atlas-ids"])
def test_the_first_keyframe_of_a_map_is_the_root_of_its_spanning_tree(
    make_store: StoreFactory, shared_allocator: bool
) -> None:
    """ORB-SLAM's initialization inserts two keyframes that share every point, then updates the connections of
    both: the map's first keyframe gets no parent (KeyFrame::UpdateConnections, mnId != InitKFid), so the two are
    not each other's parent. Also for a map whose ids do not start at 0 (a second map of an Atlas)."""
    ids = IdAllocator()
    if shared_allocator:
        earlier = make_store(ids=ids)
        add_keyframe(earlier)
        add_keyframe(earlier)
    store = make_store(ids=ids)
    free = FreeFeatures()
    k = [add_keyframe(store, 0.0), add_keyframe(store, 0.1)]
    shared(store, k, 100, free)
    store.update_connections(k[0])
    store.update_connections(k[1])
    tree = store.spanning_tree
    assert tree.parent(k[0]) is None and tree.parent(k[1]) == k[0]
    assert tree.children(k[0]) == [k[1]] and tree.children(k[1]) == []
    # keyframes inserted by local mapping afterwards, and a connections update of the first one later on
    for i in range(2, 6):
        k.append(add_keyframe(store, 0.1 * i))
        shared(store, [k[-2], k[-1]], 60, free, seed=10 * i)
        shared(store, [k[0], k[-1]], 20, free, seed=10 * i + 5)
        store.update_connections(k[-1])
    for kf in k:
        store.update_connections(kf)
    assert tree.parent(k[0]) is None
    assert [tree.parent(kf) for kf in k[1:]] == k[:-1]
    assert_tree_has_no_cycle(store)
    store.remove_keyframe(k[2])  # culling re-parents k[3] without a cycle
    assert tree.parent(k[0]) is None and tree.parent(k[3]) in (k[0], k[1])
    assert_tree_has_no_cycle(store)


def test_a_map_emptied_and_initialised_again_gets_a_new_root(store: MapStore) -> None:
    """Atlas.reset_active erases every keyframe and the map starts again: its next first keyframe is the root (ORB-SLAM3
    Map::AddKeyFrame sets mnInitKFid on an empty map); were the erased first keyframe still the root, the two
    keyframes of the new initialization would be each other's parent."""
    free = FreeFeatures()
    old = [add_keyframe(store), add_keyframe(store, 0.1)]
    shared(store, old, 30, free)
    for kf in old:
        store.update_connections(kf)
    for kf in old:
        store.remove_keyframe(kf)
    new = [add_keyframe(store), add_keyframe(store, 0.1)]
    shared(store, new, 30, free, seed=7)
    for kf in new:
        store.update_connections(kf)
    assert store.spanning_tree.parent(new[0]) is None and store.spanning_tree.parent(new[1]) == new[0]
    assert_tree_has_no_cycle(store)


# ---- restore (a saved map, slamkit/map/mapfile.py) ------------------------------------------------------------


def busy_map(store: MapStore) -> list[int]:
    """A map with every kind of state: graphs, a culled keyframe (re-parenting), culled and replaced points, counters,
    bags of words, a loop edge and a bumped epoch. Returns its keyframe ids (culled one included)."""
    free = FreeFeatures()
    k = [add_keyframe(store, 0.1 * i) for i in range(2)]
    shared(store, k, 40, free)
    for kf in k:
        store.update_connections(kf)
    for i in range(2, 6):
        k.append(add_keyframe(store, 0.1 * i))
        shared(store, [k[-2], k[-1]], 30, free, seed=10 * i)
        shared(store, [k[0], k[-1]], 16, free, seed=10 * i + 5)
        store.update_connections(k[-1])
    pids = np.array(store.point_ids(), np.int64)
    store.increase_visible(pids[::2], 4)
    store.increase_found(pids[::3], 2)
    store.replace_point(int(pids[1]), int(pids[0]))
    store.remove_point(int(pids[2]))
    store.set_keyframe_bow(k[1], BowDescription({3: 0.25, 1: 0.75}, {5: np.array([0, 2], np.int64)}))
    store.add_loop_edge(k[5], k[0])
    store.remove_keyframe(k[2])
    store.bump_epoch()
    return k


def test_restore_gives_back_every_read_and_goes_on_the_same(make_store: StoreFactory) -> None:
    """MapStore.restore of a map's contents into a new store (ids from an allocator at the saved state): every read
    answers as on the original, and the same mutations afterwards give the same map."""
    original = make_store()
    busy_map(original)
    contents = read_map_contents(original)
    restored = make_store(ids=IdAllocator(*original.ids.next_ids()))
    restored.restore(contents)
    assert not differences(contents, read_map_contents(restored))
    assert_consistent(restored)
    assert restored.origin_keyframe_id() == original.origin_keyframe_id()
    for kf in original.keyframe_ids():
        assert restored.covisibility.neighbors(kf) == original.covisibility.neighbors(kf)
        assert restored.spanning_tree.children(kf) == original.spanning_tree.children(kf)
    # the restored map goes on as the original does
    for store in (original, restored):
        free = FreeFeatures()
        free.next = {k: N_FEATS - 30 for k in store.keyframe_ids()}
        kf = add_keyframe(store, 0.9)
        shared(store, [store.keyframe_ids()[-2], kf], 25, free, seed=99)
        store.update_connections(kf)
        store.remove_keyframe(store.keyframe_ids()[1])
    assert not differences(read_map_contents(original), read_map_contents(restored))
    assert_tree_has_no_cycle(restored)


def test_restore_refuses_a_map_that_is_not_empty_or_contents_that_do_not_fit(make_store: StoreFactory) -> None:
    original = make_store()
    busy_map(original)
    contents = read_map_contents(original)
    busy = make_store(ids=IdAllocator(*original.ids.next_ids()))
    add_keyframe(busy)
    with pytest.raises(ValueError, match="not empty"):
        busy.restore(contents)
    behind = make_store()  # an allocator that never issued the saved ids
    with pytest.raises(ValueError, match="not issued"):
        behind.restore(contents)
    assert behind.n_keyframes() == 0 and behind.n_points() == 0
    point = contents.points[0]
    kf_id, feat = next(iter(point.observations.items()))
    wrong = dataclasses.replace(
        contents,
        points=(
            MapPoint(
                point.id,
                point.xyz_w,
                point.descriptor,
                point.ref_kf_id,
                point.first_kf_id,
                observations={kf_id: feat + 1},
            ),
            *contents.points[1:],
        ),
    )
    fresh = make_store(ids=IdAllocator(*original.ids.next_ids()))
    with pytest.raises(ValueError, match="observation"):
        fresh.restore(wrong)
    assert fresh.n_keyframes() == 0 and fresh.n_points() == 0


def test_add_contents_puts_another_map_in_at_once(make_store: StoreFactory) -> None:
    """MapStore.add_contents (map merging): another map of the same allocator goes in with its entities, counters,
    covisibility weights, spanning tree (its root hung under the given keyframe) and loop edges; this map's own
    reads, first keyframe and epoch are unchanged; taken ids or an unknown parent are refused before any change."""
    into = make_store()
    own = busy_map(into)
    other = make_store(ids=into.ids)
    busy_map(other)
    before = read_map_contents(into)
    incoming = read_map_contents(other)
    root = incoming.first_keyframe_id
    assert root is not None and incoming.tree[root] is None
    parent = own[0]
    into.add_contents(incoming, roots_parent=parent)
    assert_consistent(into)
    assert_tree_has_no_cycle(into)
    assert into.keyframe_ids() == sorted([*before.tree, *incoming.tree])
    assert into.spanning_tree.parent(root) == parent and root in into.spanning_tree.children(parent)
    for kf in other.keyframe_ids():
        assert into.covisibility.neighbors(kf) == other.covisibility.neighbors(kf)
        assert into.get_keyframe(kf).point_ids.tolist() == other.get_keyframe(kf).point_ids.tolist()
        if kf != root:
            assert into.spanning_tree.parent(kf) == other.spanning_tree.parent(kf)
    pids = np.array(other.point_ids(), np.int64)
    for name in ("n_visible", "n_found", "n_observations", "xyz_w"):
        np.testing.assert_array_equal(into.point_rows(pids, name), other.point_rows(pids, name))
    assert set(into.loop_edges()) == {*before.loop_edges, *incoming.loop_edges}
    assert into.origin_keyframe_id() == min(before.tree) and into.epoch == before.epoch
    for kf in before.tree:
        assert into.spanning_tree.parent(kf) == before.tree[kf]
    n_kfs, n_points = into.n_keyframes(), into.n_points()
    with pytest.raises(ValueError):
        into.add_contents(incoming)  # every id is taken now
    third = make_store(ids=into.ids)
    busy_map(third)
    with pytest.raises(ValueError):
        into.add_contents(read_map_contents(third), roots_parent=10**6)
    assert (into.n_keyframes(), into.n_points()) == (n_kfs, n_points)


def test_the_min_shared_threshold_is_the_configured_one(make_store: StoreFactory) -> None:
    store = make_store(covisibility_min_shared=25)
    k = [add_keyframe(store, 0.1 * i) for i in range(3)]
    free = FreeFeatures()
    shared(store, [k[0], k[1]], 30, free)
    shared(store, [k[0], k[2]], 20, free)
    shared(store, [k[1], k[2]], 19, free)
    for kf in k:
        store.update_connections(kf)
    # 20 < 25: the edge k0-k2 is not kept by k0's update; k2 keeps only its best (k0, 20)
    assert store.covisibility.neighbors(k[0]) == [k[1], k[2]]
    assert store.covisibility.neighbors(k[2]) == [k[0]] and store.covisibility.weight(k[1], k[2]) == 0


# ---- point rows, counters, poses ------------------------------------------------------------------------------


def test_point_rows_equal_the_entities_after_every_kind_of_mutation(store: MapStore) -> None:
    rng = np.random.default_rng(7)
    kfs = [add_keyframe(store, 0.1 * i) for i in range(6)]
    free = FreeFeatures()
    visible: dict[int, int] = {}
    found: dict[int, int] = {}

    def check() -> None:
        assert_consistent(store, visible, found)

    for i in range(60):
        observers = sorted(rng.choice(kfs, size=int(rng.integers(2, 5)), replace=False).tolist())
        pid = add_point(store, {k: free.take(k) for k in observers}, seed=i)
        visible[pid] = found[pid] = 1
    check()
    for name, shape, dtype in (
        ("xyz_w", (3,), np.float64),
        ("normal_w", (3,), np.float64),
        ("d_min_m", (), np.float64),
        ("d_max_m", (), np.float64),
        ("descriptor", (32,), np.uint8),
    ):
        ids = np.array(store.point_ids()[::3], np.int64)
        values = (rng.uniform(0, 255, (ids.size, *shape))).astype(dtype)
        store.assign_points(ids, name, values)
        check()
        np.testing.assert_array_equal(store.point_rows(ids, name), values)
        values[...] = 0  # the store keeps its own copy
        assert np.any(store.point_rows(ids, name) != 0)
    ids = np.array(store.point_ids(), np.int64)
    twice = np.concatenate([ids[:10], ids[:5]])  # an id listed twice counts twice
    store.increase_visible(twice)
    store.increase_found(ids[:3], 2)
    for p in twice.tolist():
        visible[p] += 1
    for p in ids[:3].tolist():
        found[p] += 2
    check()
    old, new = int(ids[0]), int(ids[1])
    store.replace_point(old, new)  # ORB-SLAM Replace: observations and counters move to the survivor
    visible[new] += visible.pop(old)
    found[new] += found.pop(old)
    assert not store.has_point(old)
    check()
    store.remove_observation(int(ids[2]), next(iter(store.get_point(int(ids[2])).observations)))
    check()
    store.remove_point(int(ids[3]))
    store.remove_keyframe(kfs[2])
    for p in list(visible):
        if not store.has_point(p):
            visible.pop(p), found.pop(p)
    check()
    np.testing.assert_array_equal(store.has_points(ids), [store.has_point(int(p)) for p in ids])


def test_counters_start_at_one_and_count_concurrent_increases_under_the_read_lock(store: MapStore) -> None:
    k0, k1 = add_keyframe(store), add_keyframe(store, 0.2)
    ids = np.array(shared(store, [k0, k1], 200, FreeFeatures()), np.int64)
    np.testing.assert_array_equal(store.point_rows(ids, "n_visible"), np.ones(200))
    np.testing.assert_array_equal(store.point_rows(ids, "n_found"), np.ones(200))

    def track() -> None:  # as tracking does, frame after frame, while other threads read
        for _ in range(200):
            with store.read():
                store.increase_visible(ids)
                store.increase_found(ids[::2])

    threads = [threading.Thread(target=track) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    np.testing.assert_array_equal(store.point_rows(ids, "n_visible"), np.full(200, 1 + 600))
    np.testing.assert_array_equal(store.point_rows(ids[::2], "n_found"), np.full(100, 1 + 600))
    np.testing.assert_array_equal(store.point_rows(ids[1::2], "n_found"), np.ones(100))


def test_poses_and_bags_of_words_are_set_through_the_store(store: MapStore) -> None:
    k0, k1 = add_keyframe(store), add_keyframe(store, 0.2)
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    store.set_keyframe_pose(k0, T)
    T[0, 3] = 9.0  # the store keeps a copy
    assert store.get_keyframe(k0).T_c_w[0, 3] == 1.0
    poses = np.stack([np.eye(4), np.eye(4)])
    poses[:, 2, 3] = [4.0, 5.0]
    store.set_keyframe_poses([k0, k1], poses)
    assert [store.get_keyframe(k).T_c_w[2, 3] for k in (k0, k1)] == [4.0, 5.0]
    np.testing.assert_array_equal(store.get_keyframe(k1).center_w, [0.0, 0.0, -5.0])
    bow = BowDescription({1: 1.0}, {})
    store.set_keyframe_bow(k1, bow)
    assert store.get_keyframe(k1).bow is bow


def test_epoch_is_bumped_by_one(store: MapStore) -> None:
    e = store.epoch
    assert store.bump_epoch() == e + 1 and store.epoch == e + 1


def test_origin_is_the_smallest_keyframe_left(store: MapStore) -> None:
    k = [add_keyframe(store) for _ in range(3)]
    assert store.origin_keyframe_id() == k[0]
    store.remove_keyframe(k[0])
    assert store.origin_keyframe_id() == k[1] and store.n_keyframes() == 2


# ---- the lock --------------------------------------------------------------------------------------------------


def _waits(hold: Callable[[], Any], then: Callable[[], Any]) -> bool:
    """Whether ``then()`` (a lock context) has to wait while another thread is inside ``hold()``."""
    inside, release, got_in = threading.Event(), threading.Event(), threading.Event()

    def holder() -> None:
        with hold():
            inside.set()
            release.wait(10)

    def other() -> None:
        with then():
            got_in.set()

    t1 = threading.Thread(target=holder)
    t1.start()
    assert inside.wait(10)
    t2 = threading.Thread(target=other)
    t2.start()
    waited = not got_in.wait(0.2)
    release.set()
    t1.join(10)
    t2.join(10)
    assert got_in.is_set()
    return waited


def test_the_write_lock_excludes_readers_and_writers(store: MapStore) -> None:
    assert _waits(store.write, store.read)
    assert _waits(store.read, store.write)
    assert _waits(store.write, store.write)


def test_a_writer_waiting_for_a_reader_gets_in_once_the_reader_leaves(store: MapStore) -> None:
    order: list[str] = []
    reading = threading.Event()

    def reader() -> None:
        with store.read():
            reading.set()
            time.sleep(0.05)
            order.append("read")

    def writer() -> None:
        with store.write():
            order.append("write")

    t1 = threading.Thread(target=reader)
    t1.start()
    reading.wait(5)
    t2 = threading.Thread(target=writer)
    t2.start()
    for t in (t1, t2):
        t.join(10)
    assert order == ["read", "write"]


# ---- entities are read-only outside the store ------------------------------------------------------------------


def test_writing_an_entity_behind_the_store_raises(store: MapStore) -> None:
    k0, k1 = add_keyframe(store), add_keyframe(store, 0.2)
    pid = add_point(store, {k0: 0, k1: 0})
    kf, point = store.get_keyframe(k0), store.get_point(pid)
    writes: list[Callable[[], Any]] = [
        lambda: kf.point_ids.__setitem__(0, -1),
        lambda: kf.T_c_w.__setitem__((0, 3), 1.0),
        lambda: setattr(kf, "T_c_w", np.eye(4)),
        lambda: setattr(kf, "bow", None),
        lambda: setattr(kf, "point_ids", np.full(N_FEATS, -1)),
        lambda: point.xyz_w.__setitem__(0, 1.0),
        lambda: point.normal_w.__setitem__(0, 1.0),
        lambda: point.descriptor.__setitem__(0, 1),
        lambda: setattr(point, "xyz_w", np.zeros(3)),
        lambda: setattr(point, "ref_kf_id", k1),
        lambda: point.observations.__setitem__(k1, 5),  # type: ignore[attr-defined]
        lambda: point.observations.pop(k1),  # type: ignore[attr-defined]
    ]
    for i, write in enumerate(writes):
        with pytest.raises((ValueError, TypeError, AttributeError)):
            write()
        assert_consistent(store), i
    assert kf.point_ids[0] == pid and store.get_point(pid).observations[k1] == 0
    # the graphs are handed out as read views: no mutator, and what they return is the caller's own list
    for name in ("update_connections", "remove", "add_node", "add", "change_parent"):
        assert not hasattr(store.covisibility, name) and not hasattr(store.spanning_tree, name)
    store.update_connections(k1)
    store.spanning_tree.children(k0).append(99)
    store.covisibility.neighbors(k0).append(99)
    assert store.spanning_tree.children(k0) == [k1] and store.covisibility.neighbors(k0) == [k1]


def test_copies_of_entities_are_read_only_and_belong_to_no_store(store: MapStore) -> None:
    k0, k1 = add_keyframe(store), add_keyframe(store, 0.2)
    pid = add_point(store, {k0: 0, k1: 0})
    for clone in (copy.deepcopy(store.get_point(pid)), pickle.loads(pickle.dumps(store.get_point(pid)))):
        with pytest.raises(ValueError):
            clone.xyz_w[0] = 1.0
    kf_clone = copy.deepcopy(store.get_keyframe(k0))
    with pytest.raises(ValueError):
        kf_clone.point_ids[0] = 5
    store.remove_point(pid)
    assert kf_clone.point_ids[0] == pid and store.get_keyframe(k0).point_ids[0] == -1


def test_a_map_component_without_the_whole_protocol_is_refused_when_built(registry: ComponentRegistry) -> None:
    """A ``map=`` component is checked against the full protocol when it is built, not at its first missing call
    (a class with the graphs' bookkeeping but none of the store's mutations)."""
    with pytest.raises(PluginError) as err:
        registry.instantiate("map", {"_target_": "slamkit.map.graphs.CovisibilityGraph"})
    msg = str(err.value)
    assert "does not implement MapStore" in msg
    assert all(name in msg for name in ("add_observation", "point_rows", "replace_point", "spanning_tree"))
