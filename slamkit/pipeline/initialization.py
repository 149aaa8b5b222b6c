"""Monocular map initialisation (ORB-SLAM sec. IV and Tracking::MonocularInitialization /
CreateInitialMapMonocular): find a reference frame, match the following frames to it, let the
Initializer recover the two-view geometry, then build the first two keyframes and their points, run a
global BA, and scale the map so the median scene depth is 1."""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slamkit.geometry.se3 import invert_T
from slamkit.interfaces import Initializer, MapStore, Optimizer, TwoViewResult
from slamkit.map.entities import KeyFrame, MapPoint
from slamkit.pipeline.bundle import commit_bundle, snapshot_bundle
from slamkit.pipeline.config import TrackingConfig
from slamkit.pipeline.frame import Frame
from slamkit.pipeline.keyframe_insertion import insert_keyframe
from slamkit.pipeline.map_points import refresh_points
from slamkit.pipeline.projection import match_projected, require_pinhole_image

log = logging.getLogger("slamkit.tracking")

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass(frozen=True)
class InitAttempt:
    """What one initialisation attempt did (for the run log)."""

    matches: int
    result: TwoViewResult | None
    reason: str


class MonocularInitialization:
    """The reference frame and its running matches; ``attempt(frame)`` tries to initialise with it."""

    def __init__(self, cfg: TrackingConfig, initializer: Initializer, rng: np.random.Generator) -> None:
        self.cfg = cfg
        self.initializer = initializer
        self.rng = rng
        self.reference: Frame | None = None
        self._prev_matched_px: F64 = np.zeros((0, 2))

    def reset(self) -> None:
        self.reference = None

    def _set_reference(self, frame: Frame) -> None:
        self.reference = frame
        self._prev_matched_px = frame.features.uv_undist_px.astype(np.float64).copy()

    def match(self, frame: Frame) -> tuple[I64, I64]:
        """ORB-SLAM SearchForInitialization: level-0 features of the reference searched in a window around
        where they were last matched, Hamming <= TH_LOW, ratio 0.9, rotation consistency, one-to-one
        (pipeline.matcher).

        Returns (reference feature indices, current feature indices)."""
        ref = self.reference
        assert ref is not None
        cfg = self.cfg
        q = np.flatnonzero(ref.features.level == 0)
        taken = frame.features.level != 0
        m = match_projected(
            frame.features,
            taken,
            frame.bounds,
            self._prev_matched_px[q],
            ref.features.descriptors[q],
            np.full(q.shape[0], cfg.init_search_radius_px),
            np.zeros(q.shape[0], np.int64),
            np.zeros(q.shape[0], np.int64),
            cfg.matcher.th_low,
            cfg.matcher.ratio_initialization,
            ref.features.angle_deg[q].astype(np.float64),
            cfg.matcher.rotation_bins,
            cell_px=max(10.0, cfg.init_search_radius_px / 4),
        )
        ref_idx, cur_idx = q[m.query], m.feature
        self._prev_matched_px[ref_idx] = frame.features.uv_undist_px[cur_idx]
        return ref_idx, cur_idx

    def attempt(self, frame: Frame) -> tuple[InitAttempt, tuple[I64, I64] | None]:
        """One step of initialisation with ``frame``; returns what happened and, on success, the matches."""
        cfg = self.cfg
        if self.reference is None:
            if len(frame.features) > cfg.init_min_features:
                self._set_reference(frame)
                return InitAttempt(0, None, "reference frame set"), None
            return InitAttempt(0, None, f"only {len(frame.features)} features (need > {cfg.init_min_features})"), None
        if len(frame.features) <= cfg.init_min_features:
            self.reset()
            return InitAttempt(0, None, f"only {len(frame.features)} features: reference reset"), None
        ref_idx, cur_idx = self.match(frame)
        if ref_idx.shape[0] < cfg.init_min_matches:
            # ORB-SLAM2/3 MonocularInitialization: mbReadyToInitializate = false (ORB-SLAM2: the initializer
            # deleted): the reference is dropped and the *next* frame with enough features becomes the new one
            self.reset()
            return (
                InitAttempt(
                    int(ref_idx.shape[0]),
                    None,
                    f"too few matches: {ref_idx.shape[0]} < {cfg.init_min_matches}: reference reset",
                ),
                None,
            )
        require_pinhole_image(frame.camera, "monocular initialisation (the Initializer takes undistorted pixels and K)")
        result = self.initializer.initialize(
            self.reference.features.uv_undist_px[ref_idx].astype(np.float64),
            frame.features.uv_undist_px[cur_idx].astype(np.float64),
            frame.camera.K,
            self.rng,
        )
        if not result.success:
            return InitAttempt(int(ref_idx.shape[0]), result, result.reason), None
        return InitAttempt(int(ref_idx.shape[0]), result, "initialised"), (ref_idx, cur_idx)


def new_keyframe(store: MapStore, frame: Frame, point_ids: I64 | None = None) -> KeyFrame:
    """A keyframe made from a tracked frame, not yet in the map. point_ids: (N,) the map points tracking matched
    to its features (-1 none; default none), which become observations when the store adds the keyframe."""
    assert frame.T_c_w is not None
    return KeyFrame(
        id=store.new_keyframe_id(),
        frame_index=frame.index,
        timestamp_s=frame.timestamp_s,
        T_c_w=frame.T_c_w,
        camera=frame.camera,
        features=frame.features,
        point_ids=np.full(len(frame.features), -1, np.int64) if point_ids is None else point_ids,
    )


def create_initial_map(
    store: MapStore,
    optimizer: Optimizer,
    ref: Frame,
    cur: Frame,
    ref_idx: I64,
    cur_idx: I64,
    result: TwoViewResult,
    cfg: TrackingConfig,
) -> tuple[KeyFrame, KeyFrame] | str:
    """Build the initial map from a successful two-view reconstruction, or return why it was rejected."""
    assert result.T_cur_ref is not None and result.xyz_ref is not None and result.triangulated is not None
    ref.T_c_w = np.eye(4)
    cur.T_c_w = result.T_cur_ref.copy()
    with store.write():
        kf_ini = new_keyframe(store, ref)
        kf_cur = new_keyframe(store, cur)
        insert_keyframe(store, kf_ini)
        insert_keyframe(store, kf_cur)
        for m in np.flatnonzero(result.triangulated):
            pid = store.new_point_id()
            i_ref, i_cur = int(ref_idx[m]), int(cur_idx[m])
            # first keyframe: the current one (ORB-SLAM CreateInitialMapMonocular: new MapPoint(worldPos, pKFcur),
            # mnFirstKFid = pKFcur->mnId; the age VI-B's culling counts when new_map_points_culled)
            store.add_point(
                MapPoint(
                    pid,
                    result.xyz_ref[m].astype(np.float64).copy(),
                    ref.features.descriptors[i_ref].copy(),
                    kf_ini.id,
                    kf_cur.id,
                )
            )
            store.add_observation(pid, kf_ini.id, i_ref)
            store.add_observation(pid, kf_cur.id, i_cur)
        refresh_points(store, store.point_ids())  # descriptor, normal and depth range from the two keyframes
        store.update_connections(kf_ini.id)
        store.update_connections(kf_cur.id)
        # Global BA of the two keyframes (ORB-SLAM: GlobalBundleAdjustemnt(map, 20)); the first keyframe fixed.
        snap = snapshot_bundle(
            store,
            [kf_cur.id],
            [kf_ini.id],
            store.point_ids(),
            cfg.init_ba_iterations,
            0,
            cfg.chi2.mono,
            cfg.chi2.stereo,
        )
    ba = optimizer.bundle_adjust(snap.problem)
    # ORB-SLAM GlobalBundleAdjustemnt (BundleAdjustment with bRobust): Huber kernel, no outlier pass and no
    # observation removed afterwards; the map is judged on all its points below
    ba = dataclasses.replace(ba, outlier=np.zeros_like(ba.outlier))
    with store.write():
        commit_bundle(store, snap, ba)
        depths = _depths_in(kf_ini, store)
        # ORB-SLAM3 CreateInitialMapMonocular: reset when medianDepth < 0 or pKFcur->TrackedMapPoints(1) < 50
        n_tracked = kf_cur.n_tracked_points()
        if depths.size == 0 or np.median(depths) <= 0 or n_tracked < cfg.init_min_map_points:
            reason = (
                f"wrong initialisation: median depth {np.median(depths) if depths.size else float('nan'):.3f}, "
                f"{n_tracked} tracked points (need {cfg.init_min_map_points})"
            )
            for kf_id in store.keyframe_ids():
                store.remove_keyframe(kf_id)
            return reason
        inv_median = 1.0 / float(np.median(depths))
        T_cur_w = kf_cur.T_c_w.copy()
        T_cur_w[:3, 3] *= inv_median
        store.set_keyframe_pose(kf_cur.id, T_cur_w)
        pids = np.array(store.point_ids(), np.int64)
        if pids.size:
            store.assign_points(pids, "xyz_w", store.point_rows(pids, "xyz_w") * inv_median)
        refresh_points(store, pids.tolist(), descriptors=False)
    log.info(
        "map initialised: keyframes %d/%d, %d points, model %s",
        kf_ini.frame_index,
        kf_cur.frame_index,
        store.n_points(),
        result.model,
    )
    return kf_ini, kf_cur


def create_stereo_initial_map(store: MapStore, frame: Frame) -> KeyFrame:
    """ORB-SLAM2 Tracking::StereoInitialization: the frame (pose ``frame.T_c_w``, the identity) becomes the map's
    first keyframe, inserted here as initialisation's keyframes are, and every keypoint with a depth (> 0, close or
    far) gets a map point back-projected at its depth (Frame::UnprojectStereo), observed by that keyframe; the
    points' descriptor, normal and depth range are computed. Returns the keyframe (its ``point_ids`` set)."""
    assert frame.T_c_w is not None
    feats = frame.features
    depth = feats.depth_m
    with_depth = np.flatnonzero(np.isfinite(depth) & (depth > 0))
    T_w_c = invert_T(frame.T_c_w)
    xyz = feats.unproject_stereo(with_depth, T_w_c, frame.camera.K)
    with store.write():
        kf = new_keyframe(store, frame)
        insert_keyframe(store, kf)
        created: list[int] = []
        for m, i in enumerate(with_depth.tolist()):
            pid = store.new_point_id()
            store.add_point(MapPoint(pid, xyz[m].copy(), feats.descriptors[i].copy(), kf.id, kf.id))
            store.add_observation(pid, kf.id, i)
            created.append(pid)
        refresh_points(store, created)
        store.update_connections(kf.id)
        kf = store.get_keyframe(kf.id)
    return kf


def _depths_in(kf: KeyFrame, store: MapStore) -> F64:
    """(M,) depths (z in the camera) of the points a keyframe observes."""
    pids = kf.point_ids[kf.point_ids >= 0]
    if pids.size == 0:
        return np.zeros(0)
    xyz = np.stack([store.get_point(int(p)).xyz_w for p in pids])
    return np.asarray(xyz @ kf.T_c_w[2, :3] + kf.T_c_w[2, 3])
