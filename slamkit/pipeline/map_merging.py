"""Map merging (ORB-SLAM3, Campos et al. T-RO 2021, sec. III-B; released code LoopClosing::MergeLocal / MergeLocal2):
weld the active map and a map of the Atlas in which place recognition found a common region (the merge detection
of slamkit/pipeline/loop_closing.py) into one map.

The steps, each a function here, run by ``LoopCloser.merge`` with local mapping parked:

1. **The welding windows** (:func:`welding_window`): the current keyframe and its covisible keyframes, the matched
   keyframe and its covisible keyframes (ORB-SLAM3 numTemporalKFs = 15, widened through the best covisibles of the
   window at most nMaxTries = 3 times).
2. **The active map into the matched map's frame** (:func:`moved_map` computed under the read lock,
   :func:`apply_moved_map` written under the write lock, as ORB-SLAM3 computes mTcwMerge / mPosMerge before it takes
   the map mutex): every keyframe and point of the active map moved by the similarity the detection measured (a Sim3
   for monocular: the scale too). ORB-SLAM3 moves the
   welding window first and the rest of the map after the welding BA by the same similarity, so the result is the
   same as moving the whole map at once, which is what slamkit does (one write).
3. **The matched map's entities into the active map's store** (:func:`import_map`): ORB-SLAM3's visual MergeLocal
   moves the current map's entities into the matched map and makes it active; its MergeLocal2 (the inertial one)
   moves the matched map's entities into the current map, as slamkit does. The store tracking and local mapping hold
   stays theirs (no reference to swap); the merged map keeps the active map's id and the matched map's world frame,
   and the matched map leaves the Atlas. The other map's contents are read and its spanning tree re-rooted at the
   matched keyframe before the write lock (:func:`rooted_at`); under it they go in at once
   (``MapStore.add_contents``: covisibility weights as saved, the matched keyframe hung under the current one, as
   ORB-SLAM3 re-roots the absorbed tree), then the detection's matches are fused (the current keyframe's duplicates
   replaced by the matched map's points).
4. **Duplicate fusion** (ORB-SLAM3 SearchAndFuse): the points of the matched keyframe's window projected into the
   current window, the incoming point winning; then the connections of both windows are updated.
5. **Welding BA** (:func:`welding_bundle`, ORB-SLAM3 ``Optimizer::LocalBundleAdjustment(pMainKF, vpAdjustKF,
   vpFixedKF)``): the current window's keyframes and every point the two windows see are optimized against the
   matched window, fixed; only the two windows' observations are in it (ORB-SLAM3), not the other keyframes seeing
   those points.
6. **Essential graph** of the merged map (:func:`merge_essential_graph_problem`; paper sec. III-B; the released
   code runs it for stereo/RGB-D only and moves a monocular map rigidly): the keyframes of the matched map and the
   welded windows fixed, the rest of the former active map free, so the welding BA's correction spreads over it.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from slamkit.geometry.sim3 import Sim3
from slamkit.interfaces import MapStore
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


@dataclass(frozen=True)
class MovedMap:
    """A map's keyframes and points as a similarity moves them (``moved_map``), computed before the write that
    applies them (``apply_moved_map``). kf_ids (K,) with T_c_w (K, 4, 4) their new poses; point_ids (P,) with xyz_w
    (P, 3) m, normal_w (P, 3) and the scale-invariance distances d_min_m / d_max_m (P,) m in the new frame."""

    kf_ids: list[int]
    T_c_w: F64
    point_ids: NDArray[np.int64]
    xyz_w: F64
    normal_w: F64
    d_min_m: F64
    d_max_m: F64


def moved_pose(T_c_w: F64, G_new_old: Sim3) -> F64:
    """(4, 4) T_c_w of a camera after the similarity x_new = G x_old moved its world frame: [R, t / s] of the Sim3
    T_c_w G^-1 (the map absorbs the scale, as in ORB-SLAM)."""
    return pose_of_sim3(sim3_of_pose(T_c_w) @ G_new_old.inverse())


def moved_map(store: MapStore, G_new_old: Sim3) -> MovedMap:
    """Where the similarity x_new = G x_old of its world frame takes the map (read under the read lock; nothing is
    written): keyframe poses T_i_new = [R, t / s] of the Sim3 T_i_old G^-1 (the map absorbs the scale, as in
    ORB-SLAM), point positions G x, normals R_G n, scale-invariance distances s_G d."""
    kf_ids = store.keyframe_ids()
    poses = (
        np.stack([moved_pose(store.get_keyframe(k).T_c_w, G_new_old) for k in kf_ids])
        if kf_ids
        else np.zeros((0, 4, 4))
    )
    pids = np.array(store.point_ids(), np.int64)
    M = G_new_old.matrix()
    if not pids.size:
        empty = np.zeros((0, 3))
        return MovedMap(kf_ids, poses, pids, empty, empty, np.zeros(0), np.zeros(0))
    xyz = store.point_rows(pids, "xyz_w").reshape(-1, 3) @ M[:3, :3].T + M[:3, 3]
    normal = store.point_rows(pids, "normal_w").reshape(-1, 3) @ G_new_old.R.T
    d_min = store.point_rows(pids, "d_min_m") * G_new_old.s
    d_max = store.point_rows(pids, "d_max_m") * G_new_old.s
    return MovedMap(kf_ids, poses, pids, xyz, normal, d_min, d_max)


def apply_moved_map(store: MapStore, moved: MovedMap, G_new_old: Sim3) -> None:
    """Write ``moved`` (under the write lock). Entities that came or went since it was computed (none while local
    mapping is parked: tracking adds none) are left out or moved here by ``G_new_old``."""
    if moved.kf_ids:
        keep = [i for i, k in enumerate(moved.kf_ids) if store.has_keyframe(k)]
        store.set_keyframe_poses([moved.kf_ids[i] for i in keep], moved.T_c_w[keep])
    late_kfs = sorted(set(store.keyframe_ids()) - set(moved.kf_ids))
    if late_kfs:
        store.set_keyframe_poses(
            late_kfs, np.stack([moved_pose(store.get_keyframe(k).T_c_w, G_new_old) for k in late_kfs])
        )
    if moved.point_ids.size:
        live = store.has_points(moved.point_ids)
        pids = moved.point_ids[live]
        store.assign_points(pids, "xyz_w", moved.xyz_w[live])
        store.assign_points(pids, "normal_w", moved.normal_w[live])
        store.assign_points(pids, "d_min_m", moved.d_min_m[live])
        store.assign_points(pids, "d_max_m", moved.d_max_m[live])
    late = np.setdiff1d(np.array(store.point_ids(), np.int64), moved.point_ids)
    if late.size:
        M = G_new_old.matrix()
        store.assign_points(late, "xyz_w", store.point_rows(late, "xyz_w").reshape(-1, 3) @ M[:3, :3].T + M[:3, 3])
        store.assign_points(late, "normal_w", store.point_rows(late, "normal_w").reshape(-1, 3) @ G_new_old.R.T)
        for name in ("d_min_m", "d_max_m"):
            store.assign_points(late, name, store.point_rows(late, name) * G_new_old.s)


def transform_map(store: MapStore, G_new_old: Sim3) -> None:
    """Move the whole map by the similarity x_new = G x_old of its world frame (under the write lock): ``moved_map``
    then ``apply_moved_map``."""
    apply_moved_map(store, moved_map(store, G_new_old), G_new_old)


def rooted_at(contents: MapContents, root: int) -> MapContents:
    """``contents`` with its spanning tree re-rooted at the keyframe ``root``: the chain from it up to the old root
    turned around (ORB-SLAM3 MergeLocal / MergeLocal2 rebuild the essential graph so: the matched keyframe's old parent
    becomes its child, and so on up the tree), so ``root`` is the tree's root, which ``MapStore.add_contents`` then
    hangs under the current keyframe. Pure data: computed before the write lock."""
    tree = dict(contents.tree)
    if root not in tree:
        return contents
    chain = [root]
    up = tree[root]
    while up is not None and up not in chain:
        chain.append(up)
        up = tree.get(up)
    for child, parent in zip(chain[1:], chain[:-1], strict=True):
        tree[child] = parent
    tree[root] = None
    return replace(contents, tree=tree)


def import_map(
    store: MapStore, contents: MapContents, current_kf_id: int, matches: Mapping[int, int], checked: bool = False
) -> list[int]:
    """Put another map's entities (``contents``, read with ``read_map_contents`` and re-rooted at the matched keyframe
    with ``rooted_at``; ids unique across the Atlas) into ``store`` at once (``MapStore.add_contents``, under the
    write lock), in the frame they have: keyframes, points with their counters, covisibility edges with their weights,
    the spanning tree hung under the current keyframe (ORB-SLAM3 MergeLocal2: ``mpMergeMatchedKF->ChangeParent(
    mpCurrentKF)``), loop edges. Then the detection's ``matches`` (current keyframe's feature -> the other map's point
    id): the current keyframe's point there is replaced by the other map's (MapPoint::Replace) or the feature
    observes it. checked: ``contents`` passed ``check_contents`` already (before the write lock). Returns the
    imported keyframe ids (ascending)."""
    store.add_contents(contents, roots_parent=current_kf_id, checked=checked)
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
    return [kf.id for kf in contents.keyframes]


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
    window's keyframes free, the matched window's fixed, every point either window sees, and only the two windows'
    observations of them: ORB-SLAM3 adds an edge only for a keyframe of one of the windows (``mnBALocalForMerge``),
    unlike local mapping's BA, which holds every other observer fixed. The active map's keyframes outside the current
    window carry the detection's error after the rigid move; held fixed here they kept the window (and through the
    essential graph the whole former active map) half-way between the two maps. None when there is nothing to
    optimize. Called under the read lock."""
    free = [k for k in current_window if store.has_keyframe(k)]
    fixed_window = [k for k in merge_window if store.has_keyframe(k) and k not in set(free)]
    pids = window_points(store, [*free, *fixed_window])
    if not free or not pids:
        return None
    return snapshot_bundle(store, free, fixed_window, pids, iterations_first, iterations_second, chi2_mono, chi2_stereo)


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
    "MovedMap",
    "apply_moved_map",
    "import_map",
    "merge_essential_graph_problem",
    "moved_map",
    "moved_pose",
    "rooted_at",
    "transform_map",
    "welding_bundle",
    "welding_window",
    "window_points",
]
