"""Global bundle adjustment after a loop closure (ORB-SLAM2 LoopClosing::RunGlobalBundleAdjustment, in its own
thread; ORB-SLAM sec. VII-D and the released code).

Three steps, so the optimisation can run while tracking and local mapping go on:

1. :func:`snapshot_global_ba` copies every keyframe and point of the map (under the read lock); the map's first
   keyframe is fixed (gauge).
2. The optimizer runs on the copy without any lock (10 iterations, Huber kernel, no outlier removal: ORB-SLAM2's
   ``Optimizer::GlobalBundleAdjustemnt(pMap, 10, &mbStopGBA, nLoopKF, false)``); an abort token (a new loop,
   the run stopping) stops it, and an aborted result is dropped.
3. :func:`commit_global_ba` writes the result back (under the write lock, local mapping parked): keyframes and
   points of the snapshot take their optimised values; keyframes added meanwhile are corrected through the
   spanning tree from their parent (T_child_new = T_child T_parent_before^-1 T_parent_new, ORB-SLAM2's
   ``mTcwBefGBA`` / ``mTcwGBA`` walk from the origin), and points added meanwhile move with their reference
   keyframe (X_new = T_ref_new^-1 T_ref_before X).
"""

from __future__ import annotations

import dataclasses
from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slamkit.interfaces import AbortToken, MapStore, Optimizer
from slamkit.pipeline.bundle import BundleSnapshot, commit_bundle, snapshot_bundle
from slamkit.pipeline.map_points import refresh_points
from slamkit.problems import BundleResult

F64 = NDArray[np.float64]


@dataclass
class GlobalBAOutcome:
    """What one global BA did. loop_kf_id: the keyframe whose loop started it. keyframes / points: in its
    snapshot. aborted: stopped before the end (nothing written). propagated_keyframes / propagated_points:
    added while it ran, corrected through the spanning tree / their reference keyframe. ms: optimisation wall time.
    """

    loop_kf_id: int
    keyframes: int = 0
    points: int = 0
    aborted: bool = False
    propagated_keyframes: int = 0
    propagated_points: int = 0
    ms: float = 0.0


def snapshot_global_ba(store: MapStore, iterations: int, chi2_mono: float, chi2_stereo: float) -> BundleSnapshot | None:
    """Every keyframe (the first one fixed) and every point of the map, ``iterations`` LM iterations and no
    second, outlier-free round (ORB-SLAM2 GlobalBundleAdjustemnt). None when the map has fewer than two
    keyframes. Call under the read lock."""
    kf_ids = store.keyframe_ids()
    if len(kf_ids) < 2:
        return None
    snap = snapshot_bundle(
        store, kf_ids[1:], kf_ids[:1], store.point_ids(), chi2_mono=chi2_mono, chi2_stereo=chi2_stereo
    )
    problem = dataclasses.replace(snap.problem, iterations_first=iterations, iterations_second=0)
    return dataclasses.replace(snap, problem=problem)


def optimize_global_ba(optimizer: Optimizer, snap: BundleSnapshot, abort: AbortToken | None) -> BundleResult:
    """Run the snapshot's BA (no lock held). ORB-SLAM2's global BA removes no observation: the outlier flags
    are cleared."""
    problem = snap.problem
    if problem.obs_pose.size == 0 or problem.pose_fixed.all():
        return BundleResult(problem.T_c_w, problem.xyz_w, np.zeros(problem.obs_pose.size, bool), 0.0, 0.0, 0)
    result = optimizer.bundle_adjust(problem, abort)
    return dataclasses.replace(result, outlier=np.zeros_like(result.outlier))


def commit_global_ba(store: MapStore, snap: BundleSnapshot, result: BundleResult) -> tuple[int, int]:
    """Write a global BA back and carry its correction to what was added meanwhile (see the module docstring).
    Returns (keyframes, points) corrected by propagation. Call under the write lock with local mapping parked."""
    before = {k: store.get_keyframe(k).T_c_w.copy() for k in store.keyframe_ids()}
    commit_bundle(store, snap, result)
    in_snapshot = {int(k) for k in snap.kf_ids.tolist() if store.has_keyframe(int(k))}
    corrected: dict[int, F64] = {k: store.get_keyframe(k).T_c_w.copy() for k in in_snapshot}
    tree = store.spanning_tree
    queue = deque(sorted(in_snapshot))
    propagated: list[int] = []
    while queue:
        parent = queue.popleft()
        for child in sorted(tree.children(parent)):
            if child in corrected or not store.has_keyframe(child) or child not in before:
                continue
            T_child_parent = before[child] @ np.linalg.inv(before[parent])
            corrected[child] = T_child_parent @ corrected[parent]
            propagated.append(child)
            queue.append(child)
    if propagated:
        store.set_keyframe_poses(propagated, np.stack([corrected[k] for k in propagated]))
    snap_points = {int(p) for p in snap.point_ids.tolist()}
    moved_ids: list[int] = []
    moved_xyz: list[F64] = []
    for pid in store.point_ids():
        if pid in snap_points:
            continue
        point = store.get_point(pid)
        ref = point.ref_kf_id
        if ref not in corrected or ref not in before:
            continue
        xyz_ref = before[ref][:3, :3] @ point.xyz_w + before[ref][:3, 3]
        T_new = corrected[ref]
        moved_ids.append(pid)
        moved_xyz.append(T_new[:3, :3].T @ (xyz_ref - T_new[:3, 3]))
    if moved_ids:
        store.assign_points(np.array(moved_ids, np.int64), "xyz_w", np.stack(moved_xyz))
    refresh_points(store, store.point_ids(), normals=True, descriptors=False)
    store.bump_epoch()
    return len(propagated), len(moved_ids)


__all__ = ["GlobalBAOutcome", "commit_global_ba", "optimize_global_ba", "snapshot_global_ba"]
