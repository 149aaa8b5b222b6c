"""Map merging (ORB-SLAM3, Campos et al. T-RO 2021, sec. III-B; released code LoopClosing::MergeLocal / MergeLocal2):
weld the active map and a map of the Atlas in which place recognition found a common region (the merge detection
of slamkit/pipeline/loop_closing.py) into one map.

The steps, each a function here, run by ``LoopCloser.merge`` with local mapping parked:

1. **The welding windows** (:func:`welding_window`): the current keyframe and its covisible keyframes, the matched
   keyframe and its covisible keyframes (ORB-SLAM3 numTemporalKFs = 15, widened through the best covisibles of the
   window at most nMaxTries = 3 times).
2. **The active map into the matched map's frame** (:func:`transform_map`): every keyframe and point of the active
   map moved by the similarity the detection measured (a Sim3 for monocular: the scale too). ORB-SLAM3 moves the
   welding window first and the rest of the map after the welding BA by the same similarity, so the result is the
   same as moving the whole map at once, which is what slamkit does (one write).
3. **The matched map's entities into the active map's store** (:func:`import_map`): ORB-SLAM3's visual MergeLocal
   moves the current map's entities into the matched map and makes it active; its MergeLocal2 (the inertial one)
   moves the matched map's entities into the current map, as slamkit does. The store tracking and local mapping hold
   stays theirs (no reference to swap); the merged map keeps the active map's id and the matched map's world frame,
   and the matched map leaves the Atlas. The detection's matches are fused first (the current keyframe's duplicates
   replaced by the matched map's points), so every imported keyframe, added in breadth-first order of the matched
   map's spanning tree from the matched keyframe, finds its parent among keyframes already in the map (the tree of
   the merged map has no cycle; ORB-SLAM3 re-roots the absorbed tree at the matched keyframe the same way).
4. **Duplicate fusion** (ORB-SLAM3 SearchAndFuse): the points of the matched keyframe's window projected into the
   current window, the incoming point winning; then the connections of both windows are updated.
5. **Welding BA** (:func:`welding_bundle`, ORB-SLAM3 ``Optimizer::LocalBundleAdjustment(pMainKF, vpAdjustKF,
   vpFixedKF)``): the current window's keyframes and every point the two windows see are optimized, the matched
   window and every other keyframe seeing those points are fixed.
6. **Essential graph** of the merged map (:func:`merge_essential_graph_problem`; paper sec. III-B; the released
   code runs it for stereo/RGB-D only and moves a monocular map rigidly): the keyframes of the matched map and the
   welded windows fixed, the rest of the former active map free, so the welding BA's correction spreads over it.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Mapping

import numpy as np
from numpy.typing import NDArray

from slamkit.geometry.sim3 import Sim3
from slamkit.interfaces import MapStore
from slamkit.map.entities import KeyFrame, MapPoint
from slamkit.map.mapfile_contents import MapContents
from slamkit.pipeline.bundle import BundleSnapshot, snapshot_bundle
from slamkit.pipeline.fusion import replace_point
from slamkit.pipeline.loop_correction import essential_graph_over, pose_of_sim3, sim3_of_pose
from slamkit.problems import EssentialGraphProblem

F64 = NDArray[np.float64]


def welding_window(store: MapStore, kf_id: int, n_keyframes: int, max_tries: int) -> list[int]:
    """ORB-SLAM3 MergeLocal's local window of ``kf_id``: it and its ``n_keyframes`` best covisible keyframes; while the
    window has fewer than ``n_keyframes``, at most ``max_tries`` times, the ``n_keyframes // 2`` best covisibles of
    each window keyframe join it. Keyframe ids, in the order they joined (deterministic)."""
    cov = store.covisibility
    window = [kf_id, *(cov.best_neighbors(kf_id, n_keyframes) if kf_id in cov else [])]
    seen = set(window)
    tries = 0
    while len(window) < n_keyframes and tries < max_tries:
        added = []
        for k in window:
            for j in cov.best_neighbors(k, n_keyframes // 2) if k in cov else []:
                if j not in seen:
                    seen.add(j)
                    added.append(j)
        window += added
        tries += 1
    return window


def window_points(store: MapStore, kf_ids: Iterable[int]) -> list[int]:
    """Ids of the live points the keyframes see, sorted."""
    return sorted(
        {
            int(p)
            for k in kf_ids
            if store.has_keyframe(k)
            for p in store.get_keyframe(k).point_ids.tolist()
            if p >= 0 and store.has_point(int(p))
        }
    )


def transform_map(store: MapStore, G_new_old: Sim3) -> None:
    """Move the whole map by the similarity x_new = G x_old of its world frame (under the write lock): keyframe poses
    T_i_new = [R, t / s] of the Sim3 T_i_old G^-1 (the map absorbs the scale, as in ORB-SLAM), point positions
    G x, normals R_G n, scale-invariance distances s_G d."""
    G_inv = G_new_old.inverse()
    kf_ids = store.keyframe_ids()
    if kf_ids:
        poses = np.stack([pose_of_sim3(sim3_of_pose(store.get_keyframe(k).T_c_w) @ G_inv) for k in kf_ids])
        store.set_keyframe_poses(kf_ids, poses)
    pids = np.array(store.point_ids(), np.int64)
    if not pids.size:
        return
    M = G_new_old.matrix()
    xyz = store.point_rows(pids, "xyz_w").reshape(-1, 3)
    store.assign_points(pids, "xyz_w", xyz @ M[:3, :3].T + M[:3, 3])
    store.assign_points(pids, "normal_w", store.point_rows(pids, "normal_w").reshape(-1, 3) @ G_new_old.R.T)
    for name in ("d_min_m", "d_max_m"):
        store.assign_points(pids, name, store.point_rows(pids, name) * G_new_old.s)


def _tree_order(contents: MapContents, root: int) -> list[int]:
    """The keyframes of ``contents``, breadth first over its spanning tree's edges (either direction) from ``root``,
    children by id; keyframes the tree does not reach follow in id order."""
    links: dict[int, list[int]] = {}
    for child, parent in contents.tree.items():
        if parent is not None:
            links.setdefault(child, []).append(parent)
            links.setdefault(parent, []).append(child)
    order, seen, todo = [], {root}, deque([root])
    while todo:
        k = todo.popleft()
        order.append(k)
        for j in sorted(links.get(k, [])):
            if j not in seen:
                seen.add(j)
                todo.append(j)
    order += [kf.id for kf in contents.keyframes if kf.id not in seen]
    return order


def import_map(
    store: MapStore, contents: MapContents, current_kf_id: int, matched_kf_id: int, matches: Mapping[int, int]
) -> list[int]:
    """Put another map's entities (``contents``, read with ``read_map_contents``; ids unique across the Atlas) into
    ``store`` (under its write lock), in the frame they have. First the points (with their visible/found counters),
    then the detection's ``matches`` (current keyframe's feature -> the other map's point id): the current
    keyframe's point there is replaced by the other map's (MapPoint::Replace) or the feature observes it; then the
    keyframes, breadth first over the other map's spanning tree from ``matched_kf_id``, each connected
    (``update_connections``) as it arrives, so its parent is a keyframe already in the map; then the loop edges.
    Returns the imported keyframe ids in that order."""
    for p in contents.points:
        store.add_point(
            MapPoint(p.id, p.xyz_w, p.descriptor, p.ref_kf_id, p.first_kf_id, p.normal_w, p.d_min_m, p.d_max_m)
        )
    if contents.points:
        ids = np.array([p.id for p in contents.points], np.int64)
        store.increase_visible(np.repeat(ids, np.maximum(contents.n_visible - 1, 0)))
        store.increase_found(np.repeat(ids, np.maximum(contents.n_found - 1, 0)))
    current = store.get_keyframe(current_kf_id)
    for feat, pid in sorted(matches.items()):
        if not store.has_point(pid):
            continue
        existing = int(current.point_ids[feat])
        if existing >= 0 and store.has_point(existing):
            if existing != pid:
                replace_point(store, store.get_point(existing), store.get_point(pid), refresh=False)
        elif current_kf_id not in store.get_point(pid).observations:
            store.add_observation(pid, current_kf_id, feat)
    by_id = {kf.id: kf for kf in contents.keyframes}
    order = _tree_order(contents, matched_kf_id) if matched_kf_id in by_id else [kf.id for kf in contents.keyframes]
    for k in order:
        kf = by_id[k]
        point_ids = np.array(kf.point_ids, np.int64)
        store.add_keyframe(
            KeyFrame(kf.id, kf.frame_index, kf.timestamp_s, kf.T_c_w, kf.camera, kf.features, point_ids, kf.bow)
        )
        store.update_connections(k)
    for a, b in contents.loop_edges:
        store.add_loop_edge(a, b)
    return order


def welding_bundle(
    store: MapStore,
    current_window: list[int],
    merge_window: list[int],
    iterations_first: int,
    iterations_second: int,
    chi2_mono: float,
    chi2_stereo: float,
) -> BundleSnapshot | None:
    """The welding BA's problem (ORB-SLAM3 LocalBundleAdjustment(pMainKF, vpAdjustKF, vpFixedKF)): the current
    window's keyframes free, the matched window's fixed, every point either window sees, and every other keyframe
    observing those points fixed. None when there is nothing to optimize. Called under the read lock."""
    free = [k for k in current_window if store.has_keyframe(k)]
    fixed_window = [k for k in merge_window if store.has_keyframe(k) and k not in set(free)]
    pids = window_points(store, [*free, *fixed_window])
    if not free or not pids:
        return None
    others = sorted({o for p in pids for o in store.get_point(p).observations} - set(free) - set(fixed_window))
    return snapshot_bundle(
        store, free, [*fixed_window, *others], pids, iterations_first, iterations_second, chi2_mono, chi2_stereo
    )


def merge_essential_graph_problem(
    store: MapStore,
    fixed: set[int],
    before: Mapping[int, Sim3],
    new_links: Mapping[int, set[int]],
    theta_min: int,
) -> tuple[EssentialGraphProblem, list[int]]:
    """The essential graph of the merged map (``loop_correction.essential_graph_over``) with the keyframes ``fixed``
    held (the matched map's and the welded windows'): the new links across the seam (``new_links``) measured from
    the current poses, the map's essential graph from the poses ``before`` the welding BA where given (the free
    keyframes' relative poses as the rigid move left them), else the current ones. Called under the read lock."""
    now = {k: sim3_of_pose(store.get_keyframe(k).T_c_w) for k in store.keyframe_ids()}
    links = [(i, j) for i, linked in sorted(new_links.items()) for j in sorted(linked)]
    return essential_graph_over(store, now, before, fixed, links, theta_min)


__all__ = [
    "import_map",
    "merge_essential_graph_problem",
    "transform_map",
    "welding_bundle",
    "welding_window",
    "window_points",
]
