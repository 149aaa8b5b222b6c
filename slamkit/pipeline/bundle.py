"""Building optimization problems from the map and committing their results (the map never reaches an
optimizer: it gets arrays, see slamkit/problems.py)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slamkit.errors import ConfigError
from slamkit.features import Observations
from slamkit.interfaces import AbortToken, Camera, MapStore, Optimizer
from slamkit.map.entities import MapPoint
from slamkit.pipeline.map_points import flat_observations, sorted_observations
from slamkit.problems import CAMERA_KANNALA_BRANDT, CAMERA_PINHOLE, BundleProblem, BundleResult

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def intrinsics_of(K: F64) -> F64:
    """(4,) fx, fy, cx, cy of a 3x3 intrinsic matrix."""
    return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])


def problem_camera(camera: Camera) -> dict[str, Any]:
    """The camera model fields of a pose problem for observations in ``camera``'s pipeline image:
    ``camera_model`` "pinhole" (the undistorted image: fx, fy, cx, cy say everything) or "kannala_brandt" with
    ``distortion`` = its (4,) k1..k4 (observations are raw fisheye pixels). Raises ConfigError for a camera whose
    pipeline image no optimization problem can model."""
    if camera.image_undistorted:
        return {"camera_model": CAMERA_PINHOLE, "distortion": None}
    if camera.model == CAMERA_KANNALA_BRANDT:
        return {"camera_model": CAMERA_KANNALA_BRANDT, "distortion": np.asarray(camera.dist, np.float64).copy()}
    raise ConfigError(
        f"camera model {camera.model!r}: its observations are in the raw image, which optimization problems model only "
        f"for {CAMERA_KANNALA_BRANDT!r} cameras"
    )


def rig_fields(features: Observations, idx: I64) -> dict[str, Any]:
    """The second-camera fields of a pose problem whose observations are keypoints ``idx`` (M,) of ``features``:
    for a two-camera record (``features.camera_2``) ``camera_index`` (M,) 0 / 1, ``T_c2_c1`` (4, 4), ``intrinsics2``,
    ``camera_model2``, ``distortion2``; for a one-camera record nothing (the problem's one-camera defaults)."""
    if not features.two_cameras or features.camera_2 is None or features.T_c2_c1 is None:
        return {}
    cam2 = problem_camera(features.camera_2)
    return {
        "camera_index": features.camera_index()[idx],
        "T_c2_c1": np.asarray(features.T_c2_c1, np.float64),
        "intrinsics2": intrinsics_of(features.camera_2.K),
        "camera_model2": cam2["camera_model"],
        "distortion2": cam2["distortion"],
    }


@dataclass(frozen=True)
class BundleSnapshot:
    """A bundle problem together with the map ids its rows stand for."""

    problem: BundleProblem
    kf_ids: I64
    point_ids: I64
    obs_kf_ids: I64
    obs_feature: I64
    dropped_point_ids: tuple[int, ...] = ()


def snapshot_bundle(
    store: MapStore,
    free_kf_ids: list[int],
    fixed_kf_ids: list[int],
    point_ids: list[int] | I64,
    iterations_first: int = 5,
    iterations_second: int = 10,
    chi2_mono: float = 5.991,
    chi2_stereo: float = 7.815,
    points: list[MapPoint] | None = None,
    flat: tuple[I64, I64, I64] | None = None,
) -> BundleSnapshot:
    """Copy what a (local or global) BA needs out of the map: the poses of free and fixed keyframes, the
    points, and every observation of those points by those keyframes (ORB-SLAM LocalBundleAdjustment).

    flat: the ``flat_observations`` of ``point_ids`` when the caller has them already (local BA gathers them to find
    its fixed keyframes): the caller vouches that every point is in the map; points: ``store.get_points(point_ids)``
    when the caller has them (only read when ``flat`` is None). Both are read from the store when None."""
    kf_ids = np.array(list(free_kf_ids) + list(fixed_kf_ids), np.int64)
    keyframes = [store.get_keyframe(int(k)) for k in kf_ids]
    T = np.array([kf.T_c_w for kf in keyframes], np.float64).reshape(-1, 4, 4)
    intr = np.array([intrinsics_of(kf.camera.K) for kf in keyframes]).reshape(-1, 4)
    bf = np.array([kf.features.bf for kf in keyframes], np.float64)
    camera = _bundle_camera(keyframes)
    # every observation of the points by these keyframes, in point order, then keyframe id order (C iterators
    # over the observation dictionaries and one sort: no Python loop per observation)
    if flat is None:
        if points is None:
            points = store.get_points(int(p) for p in point_ids)
        if len(points) != len(point_ids):
            missing = sorted(set(int(p) for p in point_ids) - {p.id for p in points})
            raise KeyError(f"snapshot_bundle: map points {missing[:5]} are not in the map")
        flat = flat_observations(points)
    # every point is in the map (checked above, or vouched for with ``flat``): get_points kept them all, in order,
    # so the ids of the points are point_ids themselves
    point_id_array = np.array(point_ids, np.int64).reshape(-1)
    counts, obs_kf_all, obs_feat_all = flat
    obs_point_s, obs_kf_s, obs_feat_s = sorted_observations(
        counts, obs_kf_all, obs_feat_all, np.isin(obs_kf_all, kf_ids)
    )
    by_id = np.argsort(kf_ids, kind="stable")
    obs_pose_all = by_id[np.searchsorted(kf_ids[by_id], obs_kf_s)]  # the row of each observer in kf_ids
    all_xyz = store.point_rows(point_id_array, "xyz_w").reshape(-1, 3)
    # A point behind every camera that sees it (or seen by none of these keyframes) cannot be optimized: it is
    # left out and reported, and the caller erases it (ORB-SLAM would flag all its observations as outliers).
    depth = np.einsum("ej,ej->e", T[obs_pose_all, 2, :3], all_xyz[obs_point_s]) + T[obs_pose_all, 2, 3]
    usable = np.zeros(point_id_array.size, bool)
    usable[obs_point_s[depth > 0.0]] = True
    dropped = point_id_array[~usable].tolist()
    pids = point_id_array[usable]
    xyz = all_xyz[usable]
    new_index = np.cumsum(usable) - 1
    keep = usable[obs_point_s]
    obs_pose_a = obs_pose_all[keep]
    obs_point_a = new_index[obs_point_s[keep]].astype(np.int64)
    obs_kf_a = obs_kf_s[keep]
    obs_feat_a = obs_feat_s[keep]
    E = obs_pose_a.size
    uv = np.zeros((E, 2))
    u_right = np.zeros(E)
    level = np.zeros(E, np.int64)
    scale_factor = 1.2
    order = np.argsort(obs_kf_a, kind="stable")
    by_kf = obs_kf_a[order]
    starts = np.flatnonzero(np.r_[True, by_kf[1:] != by_kf[:-1]]) if E else np.zeros(0, np.int64)
    kf_unique = by_kf[starts]  # np.unique(by_kf, return_index=True) of the sorted ids, without sorting again
    bounds = np.append(starts, E)
    for i, kf_id in enumerate(kf_unique.tolist()):  # each keyframe's features gathered with one indexing
        rows = order[bounds[i] : bounds[i + 1]]
        feats = store.get_keyframe(kf_id).features
        uv[rows] = feats.uv_undist_px[obs_feat_a[rows]]
        u_right[rows] = feats.u_right_px[obs_feat_a[rows]]
        level[rows] = feats.level[obs_feat_a[rows]]
        scale_factor = feats.scale_factor
    rig: dict[str, Any] = {}
    if any(kf.features.two_cameras for kf in keyframes):
        obs_pose_a, obs_point_a, obs_kf_a, obs_feat_a, uv, u_right, level, rig = _rig_rows(
            keyframes, obs_pose_a, obs_point_a, obs_kf_a, obs_feat_a, uv, u_right, level, intr
        )
    n_free = len(free_kf_ids)
    # a free keyframe left without observations (all its points dropped) is held fixed: nothing constrains it
    observed = np.zeros(len(kf_ids), bool)
    observed[obs_pose_a] = True
    problem = BundleProblem(
        T_c_w=T,
        pose_fixed=(np.arange(len(kf_ids)) >= n_free) | ~observed,
        intrinsics=intr,
        bf=bf,
        xyz_w=xyz,
        point_fixed=np.zeros(len(pids), bool),
        obs_pose=obs_pose_a,
        obs_point=obs_point_a,
        uv_px=uv,
        u_right_px=u_right,
        level=level,
        scale_factor=scale_factor,
        iterations_first=iterations_first,
        iterations_second=iterations_second,
        chi2_mono=chi2_mono,
        chi2_stereo=chi2_stereo,
        **camera,
        **rig,
    )
    return BundleSnapshot(problem, kf_ids, pids, obs_kf_a, obs_feat_a, tuple(dropped))


def _rig_rows(
    keyframes: list[Any],
    obs_pose: I64,
    obs_point: I64,
    obs_kf: I64,
    obs_feat: I64,
    uv: F64,
    u_right: F64,
    level: I64,
    intrinsics: F64,
) -> tuple[I64, I64, I64, I64, F64, F64, I64, dict[str, Any]]:
    """The observations of a bundle problem with two-camera keyframes (ORB-SLAM3 LocalBundleAdjustment with
    EdgeSE3ProjectXYZToBody): a recorded camera-2 keypoint is a camera-2 row; a recorded camera-1 keypoint with a
    stereo match adds a camera-2 row at its partner (ORB-SLAM3's tuple<left, right> of MapPoint::AddObservation: slamkit
    records the camera-1 index, the partner stands for the right one). An added row keeps the recorded keypoint as its
    ``obs_feature``, so an outlier there erases the keyframe's observation (ORB-SLAM3 EraseObservation(pKF) erases
    both). Returns the arrays (E', ...) and the problem's rig fields (per keyframe T_c2_c1 (K, 4, 4), intrinsics2
    (K, 4), camera_model2, distortion2; a one-camera keyframe gets the identity and its own intrinsics, unused)."""
    E = obs_pose.size
    row_of = {}
    for k, kf in enumerate(keyframes):
        row_of[int(kf.id)] = k
    cam = np.zeros(E, np.int64)
    extra: list[I64] = []
    extra_uv: list[F64] = []
    extra_level: list[I64] = []
    for kf_id in np.unique(obs_kf).tolist():
        feats = keyframes[row_of[kf_id]].features
        if not feats.two_cameras:
            continue
        rows = np.flatnonzero(obs_kf == kf_id)
        f = obs_feat[rows]
        cam[rows[f >= feats.n_left]] = 1
        partner = feats.stereo_partner()[f]
        has = partner >= 0
        extra.append(rows[has])
        extra_uv.append(feats.uv_undist_px[partner[has]].astype(np.float64))
        extra_level.append(feats.level[partner[has]].astype(np.int64))
    add = np.concatenate(extra) if extra else np.zeros(0, np.int64)
    if add.size:
        obs_pose = np.concatenate([obs_pose, obs_pose[add]])
        obs_point = np.concatenate([obs_point, obs_point[add]])
        obs_kf = np.concatenate([obs_kf, obs_kf[add]])
        obs_feat = np.concatenate([obs_feat, obs_feat[add]])
        uv = np.concatenate([uv, np.concatenate(extra_uv).reshape(-1, 2)])
        u_right = np.concatenate([u_right, np.full(add.size, np.nan)])
        level = np.concatenate([level, np.concatenate(extra_level)])
        cam = np.concatenate([cam, np.ones(add.size, np.int64)])
    K = len(keyframes)
    T21 = np.tile(np.eye(4), (K, 1, 1))
    intr2 = np.array(intrinsics, np.float64, copy=True).reshape(K, 4)
    models: set[str] = set()
    dist2: list[F64 | None] = [None] * K
    for k, kf in enumerate(keyframes):
        feats = kf.features
        if feats.two_cameras and feats.camera_2 is not None and feats.T_c2_c1 is not None:
            T21[k] = feats.T_c2_c1
            intr2[k] = intrinsics_of(feats.camera_2.K)
            c2 = problem_camera(feats.camera_2)
            models.add(c2["camera_model"])
            dist2[k] = c2["distortion"]
    if len(models) > 1:
        raise ConfigError(f"bundle adjustment over second cameras of different models {sorted(models)}: not supported")
    model2 = models.pop() if models else CAMERA_PINHOLE
    distortion2 = None
    if model2 == CAMERA_KANNALA_BRANDT:
        first = next(d for d in dist2 if d is not None)
        distortion2 = np.stack([first if d is None else d for d in dist2])
    rig = {
        "camera_index": cam,
        "T_c2_c1": T21,
        "intrinsics2": intr2,
        "camera_model2": model2,
        "distortion2": distortion2,
    }
    return obs_pose, obs_point, obs_kf, obs_feat, uv, u_right, level, rig


def _bundle_camera(keyframes: list[Any]) -> dict[str, Any]:
    """The camera model fields of a bundle problem: one model for every keyframe, distortion (K, 4) per keyframe."""
    fields = [problem_camera(kf.camera) for kf in keyframes]
    models = {f["camera_model"] for f in fields}
    if len(models) > 1:
        raise ConfigError(
            f"bundle adjustment over keyframes of different camera models {sorted(models)}: not supported"
        )
    if not fields or fields[0]["distortion"] is None:
        return {"camera_model": CAMERA_PINHOLE, "distortion": None}
    return {"camera_model": fields[0]["camera_model"], "distortion": np.stack([f["distortion"] for f in fields])}


def run_bundle(
    store: MapStore,
    optimizer: Optimizer,
    snap: BundleSnapshot,
    abort: AbortToken | None = None,
    bad_max_observations: int = 1,
) -> BundleResult:
    """Optimize a snapshot (no lock held) and commit it under the map's write lock (``bad_max_observations``:
    see commit_bundle)."""
    problem = snap.problem
    if problem.obs_pose.size == 0 or problem.pose_fixed.all():
        # nothing to optimize: only erase the points the snapshot dropped
        result = BundleResult(problem.T_c_w, problem.xyz_w, np.zeros(0, bool), 0.0, 0.0, 0)
        with store.write():
            commit_bundle(store, snap, result, bad_max_observations)
        return result
    result = optimizer.bundle_adjust(problem, abort)
    with store.write():
        commit_bundle(store, snap, result, bad_max_observations)
    return result


def commit_bundle(store: MapStore, snap: BundleSnapshot, result: BundleResult, bad_max_observations: int = 1) -> int:
    """Write optimized poses and points back, skipping entities culled meanwhile, and erase the
    observations flagged as outliers: a point one of them leaves with at most ``bad_max_observations``
    observations goes too (1: the store's own rule, a point needs two; ORB-SLAM2/3's MapPoint::EraseObservation
    sets a point bad at nObs <= 2).

    Points the snapshot left out (behind every camera) are erased. Returns the number of observations removed.
    """
    for pid in snap.dropped_point_ids:
        if store.has_point(pid):
            store.remove_point(pid)
    moved = [i for i, k in enumerate(snap.kf_ids.tolist()) if not snap.problem.pose_fixed[i] and store.has_keyframe(k)]
    store.set_keyframe_poses(snap.kf_ids[moved].tolist(), result.T_c_w[moved])
    alive = np.flatnonzero(store.has_points(snap.point_ids))  # one array lookup, not a call per point
    store.assign_points(snap.point_ids[alive], "xyz_w", result.xyz_w[alive])
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
        if store.has_point(pid) and len(store.get_point(pid).observations) <= bad_max_observations:
            store.remove_point(pid)
    return removed
