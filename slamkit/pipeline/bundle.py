"""Building optimization problems from the map and committing their results (the map never reaches an
optimizer: it gets arrays, see slamkit/problems.py)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slamkit.interfaces import AbortToken, Optimizer
from slamkit.map.store import InMemoryMapStore
from slamkit.problems import BundleProblem, BundleResult

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def intrinsics_of(K: F64) -> F64:
    """(4,) fx, fy, cx, cy of a 3x3 intrinsic matrix."""
    return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])


@dataclass(frozen=True)
class BundleSnapshot:
    """A bundle problem together with the map ids its rows stand for."""

    problem: BundleProblem
    kf_ids: I64
    point_ids: I64
    obs_kf_ids: I64
    obs_feature: I64


def snapshot_bundle(
    store: InMemoryMapStore,
    free_kf_ids: list[int],
    fixed_kf_ids: list[int],
    point_ids: list[int],
    iterations_first: int = 5,
    iterations_second: int = 10,
    chi2_mono: float = 5.991,
    chi2_stereo: float = 7.815,
) -> BundleSnapshot:
    """Copy what a (local or global) BA needs out of the map: the poses of free and fixed keyframes, the
    points, and every observation of those points by those keyframes (ORB-SLAM LocalBundleAdjustment)."""
    kf_ids = np.array(list(free_kf_ids) + list(fixed_kf_ids), np.int64)
    kf_row = {int(k): i for i, k in enumerate(kf_ids)}
    pids = np.array(point_ids, np.int64)
    T = np.stack([store.get_keyframe(int(k)).T_c_w for k in kf_ids])
    intr = np.stack([intrinsics_of(store.get_keyframe(int(k)).camera.K) for k in kf_ids])
    xyz = np.stack([store.get_point(int(p)).xyz_w for p in pids]) if len(pids) else np.zeros((0, 3))
    obs_pose, obs_point, obs_kf, obs_feat = [], [], [], []
    for j, pid in enumerate(pids):
        for kf_id, feat in sorted(store.get_point(int(pid)).observations.items()):
            row = kf_row.get(kf_id)
            if row is not None:
                obs_pose.append(row)
                obs_point.append(j)
                obs_kf.append(kf_id)
                obs_feat.append(feat)
    obs_pose_a = np.array(obs_pose, np.int64)
    obs_feat_a = np.array(obs_feat, np.int64)
    obs_kf_a = np.array(obs_kf, np.int64)
    uv = np.zeros((len(obs_pose), 2))
    level = np.zeros(len(obs_pose), np.int64)
    scale_factor = 1.2
    for kf_id in np.unique(obs_kf_a):
        sel = obs_kf_a == kf_id
        feats = store.get_keyframe(int(kf_id)).features
        uv[sel] = feats.uv_undist_px[obs_feat_a[sel]]
        level[sel] = feats.level[obs_feat_a[sel]]
        scale_factor = feats.scale_factor
    n_free = len(free_kf_ids)
    problem = BundleProblem(
        T_c_w=T,
        pose_fixed=np.arange(len(kf_ids)) >= n_free,
        intrinsics=intr,
        bf=np.zeros(len(kf_ids)),
        xyz_w=xyz,
        point_fixed=np.zeros(len(pids), bool),
        obs_pose=obs_pose_a,
        obs_point=np.array(obs_point, np.int64),
        uv_px=uv,
        u_right_px=np.full(len(obs_pose), np.nan),
        level=level,
        scale_factor=scale_factor,
        iterations_first=iterations_first,
        iterations_second=iterations_second,
        chi2_mono=chi2_mono,
        chi2_stereo=chi2_stereo,
    )
    return BundleSnapshot(problem, kf_ids, pids, obs_kf_a, obs_feat_a)


def run_bundle(
    store: InMemoryMapStore, optimizer: Optimizer, snap: BundleSnapshot, abort: AbortToken | None = None
) -> BundleResult:
    """Optimize a snapshot (no lock held) and commit it under the map's write lock."""
    result = optimizer.bundle_adjust(snap.problem, abort)
    with store.write():
        commit_bundle(store, snap, result)
    return result


def commit_bundle(store: InMemoryMapStore, snap: BundleSnapshot, result: BundleResult) -> int:
    """Write optimized poses and points back, skipping entities culled meanwhile, and erase the
    observations flagged as outliers (points left with fewer than 2 observations go too).

    Returns the number of observations removed.
    """
    for i, kf_id in enumerate(snap.kf_ids):
        if not snap.problem.pose_fixed[i] and store.has_keyframe(int(kf_id)):
            store.get_keyframe(int(kf_id)).T_c_w = result.T_c_w[i].copy()
    for j, pid in enumerate(snap.point_ids):
        if store.has_point(int(pid)):
            store.get_point(int(pid)).xyz_w = result.xyz_w[j].copy()
    removed = 0
    for e in np.flatnonzero(result.outlier):
        pid = int(snap.point_ids[snap.problem.obs_point[e]])
        kf_id = int(snap.obs_kf_ids[e])
        if not store.has_point(pid) or not store.has_keyframe(kf_id):
            continue
        point = store.get_point(pid)
        if point.observations.get(kf_id) != int(snap.obs_feature[e]):
            continue
        store.remove_observation(pid, kf_id)
        removed += 1
    return removed
