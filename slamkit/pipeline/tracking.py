"""Tracking (ORB-SLAM sec. V): ORB extraction, initial pose from the constant-velocity motion model (or the
reference keyframe), motion-only BA, tracking of the local map, and the new-keyframe decision.

``Tracker.step(frame_data)`` handles one frame and returns a ``TrackingOutcome``; new keyframes it decides
to create are handed to local mapping by the runner (it does not insert them in the map itself).
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections import Counter
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from enum import StrEnum
from itertools import chain

import cv2
import numpy as np
from numpy.typing import NDArray

from slamkit.geometry.se3 import SE3, invert_T
from slamkit.interfaces import BowDescription, Camera, FrontEnd, Initializer, MapStore, Optimizer, PlaceRecognizer
from slamkit.map.atlas import Atlas
from slamkit.map.entities import KeyFrame, MapPoint
from slamkit.pipeline.bundle import intrinsics_of, problem_camera
from slamkit.pipeline.config import TrackingConfig
from slamkit.pipeline.frame import Frame, ImageBounds
from slamkit.pipeline.initialization import MonocularInitialization, create_initial_map, new_keyframe
from slamkit.pipeline.lost import LostDecision, LostPolicy, LostRecord, decide_when_lost
from slamkit.pipeline.map_points import predict_level
from slamkit.pipeline.matching import hamming_matrix, resolve_one_to_one, rotation_consistent
from slamkit.pipeline.pose_optimization import optimize_pose as motion_only_ba
from slamkit.pipeline.projection import frustum_test, match_projected, project_points, radius_by_viewing_cos
from slamkit.problems import PoseOnlyProblem, PoseOnlyResult
from slamkit.sensors import FrameData

log = logging.getLogger("slamkit.tracking")

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: Keyframes of the local map K2 taken from each K1 keyframe's covisibility neighbours (ORB-SLAM code: 10).
_K2_NEIGHBORS_PER_KF = 10
#: ORB-SLAM Relocalization: at least 15 BoW matches, PnP needs 10 inliers (its BoW ratio: pipeline.matcher).
_RELOC_MIN_BOW_MATCHES = 15
_RELOC_MIN_PNP_INLIERS = 10


class TrackingState(StrEnum):
    NOT_INITIALIZED = "not_initialized"
    OK = "ok"
    LOST = "lost"


@dataclass
class TrackingOutcome:
    """What tracking did with one frame.

    T_c_w: (4, 4) estimated pose (None when not tracked). inliers: map points matched after the last pose
    optimization. new_keyframes: keyframes to hand to local mapping (``already_in_map`` for the two made by
    initialisation). timings_ms: per stage.
    """

    frame_index: int
    timestamp_s: float
    state: TrackingState
    T_c_w: F64 | None
    n_features: int
    inliers: int
    method: str
    new_keyframes: list[KeyFrame] = field(default_factory=list)
    already_in_map: bool = False
    timings_ms: dict[str, float] = field(default_factory=dict)
    message: str = ""


class Tracker:
    """The tracking thread's logic, one frame at a time (deterministic given the rng)."""

    def __init__(
        self,
        cfg: TrackingConfig,
        frontend: FrontEnd,
        initializer: Initializer,
        optimizer: Optimizer,
        atlas: Atlas,
        rng: np.random.Generator,
        place: PlaceRecognizer | None = None,
        pose_optimizer: Callable[[PoseOnlyProblem], PoseOnlyResult] | None = None,
    ) -> None:
        """frontend: turns each packet into the frame's observation record (it holds the feature extractors).
        pose_optimizer: motion-only BA of tracking; default the compiled one of
        slamkit.pipeline.pose_optimization (same algorithm as ``Optimizer.optimize_pose``, a few hundred times
        cheaper and GIL-free); pass ``optimizer.optimize_pose`` to run it through the optimizer backend."""
        self.cfg = cfg
        self.frontend = frontend
        self.optimizer = optimizer
        self.optimize_pose = pose_optimizer or motion_only_ba
        self.atlas = atlas  # the maps; tracking works on the active one (``store``)
        self.lost_policy = LostPolicy(cfg.reset_lost_map_max_keyframes, cfg.time_recently_lost_s)
        self._lost_since_s: float | None = None  # timestamp of the first frame of the current lost spell
        self.place = place  # bag of words: reference-keyframe matching and relocalization (ORB-SLAM V-B, V-C)
        self.relocalizations = 0
        self.state = TrackingState.NOT_INITIALIZED
        self.init = MonocularInitialization(cfg, initializer, rng)
        self.last_frame: Frame | None = None
        self.velocity: F64 | None = None  # T_cur_last of the last two tracked frames
        self.reference_kf_id: int | None = None
        self.last_kf_frame_index = -(10**9)
        self.last_reloc_frame_index = -(10**9)
        self._bounds: dict[int, ImageBounds] = {}
        self._last_T_l_r: F64 | None = None
        self._frame_bow: BowDescription | None = None
        self._mapping_wait_ms: float | None = None  # time the last keyframe decision spent in on_mapping_busy
        self.reset_guard: Callable[[], AbstractContextManager[None]] = contextlib.nullcontext
        # the threaded runner says no while local mapping is parked for loop closing
        self.keyframes_allowed: Callable[[], bool] = lambda: True
        # a keyframe is wanted but local mapping is busy (V-E condition 2): True inserts it anyway
        self.on_mapping_busy: Callable[[], bool] = lambda: False

    @property
    def store(self) -> MapStore:
        """The active map of the Atlas."""
        return self.atlas.active

    # ---- public ------------------------------------------------------------------------------

    def warm_up(self, camera: Camera) -> None:
        """Run the front end's feature extractors once on a synthetic image and throw the result away (the first
        extraction loads compiled kernels: 20-30 ms a timed run should not spend on its first frame). Changes no
        state of the tracker."""
        self.frontend.warm_up(camera)

    def step(self, data: FrameData, camera: Camera, mapping_idle: bool = True) -> TrackingOutcome:
        """Track one frame. camera: the dataset's (left) camera."""
        t0 = time.perf_counter()
        initializing = self.state == TrackingState.NOT_INITIALIZED
        # ORB-SLAM extracts twice the features on frames used for monocular initialisation: the front end's job
        features = self.frontend.observe(data, camera, initializing)
        t1 = time.perf_counter()
        frame = Frame.create(data.index, data.timestamp_s, camera, features, self._bounds_of(camera))
        timings = {"extract_ms": (t1 - t0) * 1e3}
        outcome = self._initialize(frame) if initializing else self._track(frame, timings, mapping_idle)
        timings["track_ms"] = (time.perf_counter() - t0) * 1e3
        outcome.timings_ms.update(timings)
        return outcome

    def reset(self) -> None:
        """Erase the active map's keyframes and start initialising again (inside ``reset_guard``: the threaded
        runner parks local mapping and loop closing there and drops their queued keyframes)."""
        with self.reset_guard():
            self.atlas.reset_active()
        self._restart()

    def start_new_map(self) -> None:
        """Keep the active map in the Atlas and initialise a new active map (ORB-SLAM3 CreateMapInAtlas; inside
        ``reset_guard``, as ``reset``)."""
        with self.reset_guard():
            self.atlas.create_map()
        self._restart()

    def _restart(self) -> None:
        self._lost_since_s = None
        self.state = TrackingState.NOT_INITIALIZED
        self.init.reset()
        self.last_frame = None
        self.velocity = None
        self.reference_kf_id = None

    # ---- initialisation ------------------------------------------------------------------------

    def _initialize(self, frame: Frame) -> TrackingOutcome:
        attempt, matches = self.init.attempt(frame)
        outcome = TrackingOutcome(
            frame.index,
            frame.timestamp_s,
            TrackingState.NOT_INITIALIZED,
            None,
            len(frame.features),
            0,
            "initialize",
            message=attempt.reason,
        )
        if matches is None or attempt.result is None:
            return outcome
        ref = self.init.reference
        assert ref is not None
        made = create_initial_map(
            self.store, self.optimizer, ref, frame, matches[0], matches[1], attempt.result, self.cfg
        )
        if isinstance(made, str):
            self.init.reset()
            outcome.message = made
            return outcome
        kf_ini, kf_cur = made
        frame.T_c_w = kf_cur.T_c_w.copy()
        frame.point_ids = kf_cur.point_ids.copy()
        frame.ref_kf_id = kf_cur.id
        self.reference_kf_id = kf_cur.id
        self.last_kf_frame_index = frame.index
        self.last_frame = frame
        self.velocity = None
        self.state = TrackingState.OK
        self.init.reset()
        outcome.state = TrackingState.OK
        outcome.T_c_w = frame.T_c_w.copy()
        outcome.inliers = kf_cur.n_tracked_points()
        outcome.new_keyframes = [kf_ini, kf_cur]
        outcome.already_in_map = True
        outcome.message = f"initialised ({attempt.result.model}, {attempt.matches} matches)"
        return outcome

    # ---- tracking --------------------------------------------------------------------------------

    def _track(self, frame: Frame, timings: dict[str, float], mapping_idle: bool) -> TrackingOutcome:
        cfg = self.cfg
        t0 = time.perf_counter()
        with self.store.read():
            method = "lost"
            ok = False
            self._frame_bow = None
            if self.state == TrackingState.LOST:
                method = "relocalization"
                ok = self._relocalize(frame)
                if ok:
                    self.last_reloc_frame_index = frame.index
                    self.relocalizations += 1
            elif self.state == TrackingState.OK and self.last_frame is not None:
                self._update_last_frame()
                if self.velocity is not None:
                    ok = self._track_motion_model(frame)
                    method = "motion_model"
                if not ok:
                    ok = self._track_reference_keyframe(frame)
                    method = "reference_keyframe"
            t1 = time.perf_counter()
            inliers = 0
            if ok:
                inliers = self._track_local_map(frame)
                recent_reloc = frame.index < self.last_reloc_frame_index + cfg.keyframe_min_frames_since_reloc
                needed = cfg.min_local_map_inliers_after_reloc if recent_reloc else cfg.min_local_map_inliers
                ok = inliers >= needed
            t2 = time.perf_counter()
        timings["initial_pose_ms"] = (t1 - t0) * 1e3
        timings["local_map_ms"] = (t2 - t1) * 1e3
        if not ok:
            return self._lost(frame, method)
        assert frame.T_c_w is not None
        self._lost_since_s = None
        if method == "relocalization" or self.last_frame is None or self.last_frame.T_c_w is None:
            self.velocity = None
        else:
            # re-orthonormalised: products of poses drift off SO(3) and optimizers reject them
            self.velocity = SE3.from_matrix(frame.T_c_w @ invert_T(self.last_frame.T_c_w), orthonormalize=True).matrix()
        self.state = TrackingState.OK
        frame.point_ids[frame.outlier] = -1
        frame.outlier[:] = False
        frame.ref_kf_id = self.reference_kf_id
        outcome = TrackingOutcome(
            frame.index, frame.timestamp_s, TrackingState.OK, frame.T_c_w.copy(), len(frame.features), inliers, method
        )
        self._mapping_wait_ms = None
        wants_keyframe = self._need_new_keyframe(frame, inliers, mapping_idle)
        if self._mapping_wait_ms is not None:
            timings["mapping_wait_ms"] = self._mapping_wait_ms
        if wants_keyframe:
            kf = new_keyframe(self.store, frame, frame.point_ids)
            outcome.new_keyframes = [kf]
            self.reference_kf_id = kf.id
            frame.ref_kf_id = kf.id
            self.last_kf_frame_index = frame.index
        self.last_frame = frame
        self._last_T_l_r = self._relative_to_reference(frame)
        return outcome

    def _relative_to_reference(self, frame: Frame) -> F64 | None:
        ref = frame.ref_kf_id
        if ref is None or frame.T_c_w is None or not self.store.has_keyframe(ref):
            return None
        return frame.T_c_w @ invert_T(self.store.get_keyframe(ref).T_c_w)

    def _update_last_frame(self) -> None:
        """ORB-SLAM UpdateLastFrame: the last frame's pose follows its reference keyframe, so corrections of
        the map (local BA, loop closing) reach the motion model's starting point."""
        last = self.last_frame
        if last is None or self._last_T_l_r is None or last.ref_kf_id is None:
            return
        if self.store.has_keyframe(last.ref_kf_id):
            last.T_c_w = self._last_T_l_r @ self.store.get_keyframe(last.ref_kf_id).T_c_w

    def _bow_of(self, frame: Frame) -> BowDescription:
        assert self.place is not None
        if self._frame_bow is None:
            self._frame_bow = self.place.transform(frame.features.descriptors)
        return self._frame_bow

    def _lost(self, frame: Frame, method: str) -> TrackingOutcome:
        self.state = TrackingState.LOST
        self.velocity = None
        msg = f"tracking lost at frame {frame.index} ({method})"
        if self._lost_since_s is None:
            self._lost_since_s = frame.timestamp_s
        n_kfs = self.store.n_keyframes()
        decision = decide_when_lost(LostRecord(n_kfs, frame.timestamp_s - self._lost_since_s), self.lost_policy)
        if decision == LostDecision.RESET_MAP:
            msg += f"; the map has {n_kfs} keyframes: reset and initialise again"
            self.reset()
        elif decision == LostDecision.NEW_MAP:
            limit_s = self.lost_policy.time_recently_lost_s
            msg += f"; relocalization failed for {limit_s:g} s: the map ({n_kfs} keyframes) stays in the Atlas"
            msg += ", a new map starts"
            self.start_new_map()
        log.info(msg)
        return TrackingOutcome(
            frame.index, frame.timestamp_s, self.state, None, len(frame.features), 0, method, message=msg
        )

    def _bounds_of(self, camera: Camera) -> ImageBounds:
        key = id(camera)
        if key not in self._bounds:
            self._bounds[key] = ImageBounds.of(camera)
        return self._bounds[key]

    def _valid_point_ids(self, point_ids: I64) -> NDArray[np.bool_]:
        """(N,) bool: the entry names a point that is in the map."""
        return self.store.has_points(point_ids)

    def _points(self, point_ids: I64) -> list[MapPoint]:
        """The map points of (K,) ids that are all in the map."""
        return list(map(self.store.get_point, point_ids.tolist()))

    def _optimize_pose(self, frame: Frame, T_init: F64) -> int:
        """Motion-only BA on the frame's matches; marks outliers; returns the inlier count."""
        idx = np.flatnonzero(frame.point_ids >= 0)
        frame.outlier[:] = False
        if idx.size < 3:
            return 0
        xyz = self.store.point_rows(frame.point_ids[idx], "xyz_w")
        feats = frame.features
        problem = PoseOnlyProblem(
            T_c_w_init=T_init,
            xyz_w=xyz,
            uv_px=feats.uv_undist_px[idx].astype(np.float64),
            u_right_px=feats.u_right_px[idx].astype(np.float64),
            level=feats.level[idx].astype(np.int64),
            intrinsics=intrinsics_of(frame.camera.K),
            bf=feats.bf,
            scale_factor=feats.scale_factor,
            chi2_mono=self.cfg.chi2.mono,
            chi2_stereo=self.cfg.chi2.stereo,
            rounds=self.cfg.pose_rounds,
            iterations_per_round=self.cfg.pose_iterations_per_round,
            **problem_camera(frame.camera),
        )
        result = self.optimize_pose(problem)
        frame.T_c_w = result.T_c_w
        frame.outlier[idx] = ~result.inliers
        return int(result.inliers.sum())

    def _discard_outliers(self, frame: Frame) -> int:
        frame.point_ids[frame.outlier] = -1
        frame.outlier[:] = False
        return int(np.count_nonzero(frame.point_ids >= 0))

    def _track_motion_model(self, frame: Frame) -> bool:
        """V-B: predict the pose with constant velocity, search the last frame's points around their
        projection (radius th * scale of their level, wider when too few), optimize the pose."""
        cfg = self.cfg
        last = self.last_frame
        assert last is not None and last.T_c_w is not None and self.velocity is not None
        T_pred = SE3.from_matrix(self.velocity @ last.T_c_w, orthonormalize=True).matrix()
        valid = np.flatnonzero(self._valid_point_ids(last.point_ids) & ~last.outlier)
        if valid.size == 0:
            return False
        pids = last.point_ids[valid]
        xyz = self.store.point_rows(pids, "xyz_w")
        desc = self.store.point_rows(pids, "descriptor")
        uv, _, inside = project_points(T_pred, xyz, frame.camera)
        inside &= frame.bounds.contains(np.where(np.isfinite(uv), uv, -1e9))
        q = np.flatnonzero(inside)
        last_level = last.features.level[valid[q]].astype(np.int64)
        scale = np.power(frame.features.scale_factor, last_level)
        for th in (cfg.motion_model_search_radius_px, 2.0 * cfg.motion_model_search_radius_px):
            frame.point_ids[:] = -1
            m = match_projected(
                frame.features,
                np.zeros(len(frame.features), bool),
                frame.bounds,
                uv[q],
                desc[q],
                th * scale,
                last_level - 1,
                last_level + 1,
                cfg.matcher.th_high,
                None,
                last.features.angle_deg[valid[q]].astype(np.float64),
                cfg.matcher.rotation_bins,
            )
            frame.point_ids[m.feature] = pids[q[m.query]]
            if len(m) >= cfg.min_motion_model_matches:
                break
        if np.count_nonzero(frame.point_ids >= 0) < cfg.min_motion_model_matches:
            return False
        self._optimize_pose(frame, T_pred)
        return self._discard_outliers(frame) >= cfg.min_inliers_after_pose_opt

    def _track_reference_keyframe(self, frame: Frame) -> bool:
        """V-B fallback: match the reference keyframe's map points by descriptor (nearest/second ratio 0.7,
        rotation consistency) and optimize from the last pose. ORB-SLAM restricts the candidates with the
        bag of words; without a place recognizer all features are candidates."""
        cfg = self.cfg
        if self.reference_kf_id is None or not self.store.has_keyframe(self.reference_kf_id):
            return False
        kf = self.store.get_keyframe(self.reference_kf_id)
        valid = self._valid_point_ids(kf.point_ids)
        feats_kf = np.flatnonzero(valid)
        if feats_kf.size == 0 or len(frame.features) == 0:
            return False
        if self.place is not None and kf.bow is not None:
            pairs = self.place.match(
                kf.features,
                kf.bow,
                frame.features,
                self._bow_of(frame),
                cfg.matcher.ratio_reference_kf,
                valid,
                None,
                max_distance=cfg.matcher.th_low,
                rotation_bins=cfg.matcher.rotation_bins,
            )
            frame.point_ids[:] = -1
            frame.point_ids[pairs[:, 1]] = kf.point_ids[pairs[:, 0]]
            if pairs.shape[0] < cfg.min_reference_kf_matches:
                return False
            assert self.last_frame is not None and self.last_frame.T_c_w is not None
            self._optimize_pose(frame, self.last_frame.T_c_w)
            return self._discard_outliers(frame) >= cfg.min_inliers_after_pose_opt
        dist = hamming_matrix(kf.features.descriptors[feats_kf], frame.features.descriptors)
        order = np.argsort(dist, axis=1, kind="stable")
        best = order[:, 0]
        rows = np.arange(feats_kf.size)
        d1 = dist[rows, best]
        d2 = dist[rows, order[:, 1]] if dist.shape[1] > 1 else np.full(feats_kf.size, 1 << 30)
        ok = (d1 <= cfg.matcher.th_low) & (d1 < cfg.matcher.ratio_reference_kf * d2)
        q = np.flatnonzero(ok)
        keep = resolve_one_to_one(q, best[q], d1[q])
        q = q[keep]
        angle_diff = kf.features.angle_deg[feats_kf[q]].astype(np.float64) - frame.features.angle_deg[best[q]]
        q = q[rotation_consistent(angle_diff, cfg.matcher.rotation_bins)]
        frame.point_ids[:] = -1
        frame.point_ids[best[q]] = kf.point_ids[feats_kf[q]]
        if q.size < cfg.min_reference_kf_matches:
            return False
        assert self.last_frame is not None and self.last_frame.T_c_w is not None
        self._optimize_pose(frame, self.last_frame.T_c_w)
        return self._discard_outliers(frame) >= cfg.min_inliers_after_pose_opt

    def _local_keyframes(self, frame: Frame) -> list[int]:
        """V-D: K1 (keyframes sharing points with the frame), then K2 (their best covisible neighbours,
        spanning-tree children and parent), at most ``local_map_covisible_keyframes``; sets K_ref."""
        matched = self._points(frame.point_ids[frame.point_ids >= 0])
        counts = Counter(chain.from_iterable(p.observations for p in matched))
        if not counts:
            return []
        k1 = sorted(counts, key=lambda k: (-counts[k], k))
        self.reference_kf_id = k1[0]
        limit = self.cfg.local_map_covisible_keyframes
        local = list(k1[:limit])
        seen = set(local)
        tree = self.store.spanning_tree
        for kf_id in list(local):
            if len(local) >= limit:
                break
            extra = self.store.covisibility.best_neighbors(kf_id, _K2_NEIGHBORS_PER_KF)
            extra += tree.children(kf_id)
            parent = tree.parent(kf_id)
            if parent is not None:
                extra.append(parent)
            for other in extra:
                if other not in seen and len(local) < limit and self.store.has_keyframe(other):
                    local.append(other)
                    seen.add(other)
        return local

    def _track_local_map(self, frame: Frame) -> int:
        """V-D: project the local map's points with the five filters, match, optimize the pose again."""
        frame.point_ids[~self._valid_point_ids(frame.point_ids)] = -1
        local_kfs = self._local_keyframes(frame)
        matched = np.unique(frame.point_ids[frame.point_ids >= 0])
        self.store.increase_visible(matched)
        if local_kfs:
            ids = np.concatenate([self.store.get_keyframe(k).point_ids for k in local_kfs])
            candidates = np.setdiff1d(np.unique(ids[ids >= 0]), matched, assume_unique=True)
            if candidates.size:
                self._search_local_points(frame, candidates.astype(np.int64))
        assert frame.T_c_w is not None
        self._optimize_pose(frame, frame.T_c_w)
        found = frame.point_ids[(frame.point_ids >= 0) & ~frame.outlier]
        if found.size == 0:
            return 0
        self.store.increase_found(found)
        return int(np.count_nonzero(self.store.point_rows(found, "n_observations") > 0))

    def _search_local_points(self, frame: Frame, candidates: I64) -> None:
        """ORB-SLAM SearchLocalPoints: the frustum test of every candidate (sorted point ids not matched yet),
        then the search around the projections of the visible ones. Attributes are read only as far as a
        point gets: the position of all, the viewing data of those projecting into the image, the descriptor
        of the visible ones."""
        cfg = self.cfg
        feats = frame.features
        assert frame.T_c_w is not None
        store = self.store
        xyz = store.point_rows(candidates, "xyz_w")
        uv, _, in_image = project_points(frame.T_c_w, xyz, frame.camera)
        in_image &= frame.bounds.contains(np.where(np.isfinite(uv), uv, -1e9))
        s = np.flatnonzero(in_image)
        if s.size == 0:
            return
        near = candidates[s]
        test = frustum_test(
            frame.T_c_w,
            frame.camera,
            frame.bounds,
            xyz[s],
            store.point_rows(near, "normal_w"),
            store.point_rows(near, "d_min_m"),
            store.point_rows(near, "d_max_m"),
            cfg.local_map_min_view_cos,
            feats.scale_factor,
            feats.n_levels,
        )
        v = np.flatnonzero(test.visible)
        visible = near[v]
        store.increase_visible(visible)
        recent = frame.index < self.last_reloc_frame_index + 2
        th = cfg.local_map_search_radius_relocalized_px if recent else cfg.local_map_search_radius_px
        level = test.predicted_level[v]
        radius = th * radius_by_viewing_cos(test.view_cos[v]) * np.power(feats.scale_factor, level)
        m = match_projected(
            feats,
            frame.point_ids >= 0,
            frame.bounds,
            test.uv_px[v],
            store.point_rows(visible, "descriptor"),
            radius,
            level - 1,
            level,
            cfg.matcher.th_high,
            cfg.matcher.ratio_local_map,
            None,
            None,
        )
        frame.point_ids[m.feature] = candidates[s[v[m.query]]]

    def _need_new_keyframe(self, frame: Frame, inliers: int, mapping_idle: bool) -> bool:
        """The four conditions of V-E. Conditions 1, 3 and 4 are read from the map under its read lock; when
        only condition 2 fails (local mapping busy, fewer than 20 frames since the last keyframe),
        ``on_mapping_busy`` is told: the threaded runner then stops the running local BA ("a signal is sent
        to stop local BA") and, when playing as fast as possible, waits for local mapping and returns True."""
        cfg = self.cfg
        if not self.keyframes_allowed():
            return False  # local mapping is stopped for a loop correction (ORB-SLAM NeedNewKeyFrame)
        with self.store.read():
            n_kfs = self.store.n_keyframes()
            if (
                frame.index < self.last_reloc_frame_index + cfg.keyframe_min_frames_since_reloc
                and n_kfs > cfg.keyframe_min_frames_since_reloc
            ):
                return False  # condition 1
            if inliers < cfg.keyframe_min_tracked_points:
                return False  # condition 3
            if self.reference_kf_id is not None and self.store.has_keyframe(self.reference_kf_id):
                ref = self.store.get_keyframe(self.reference_kf_id)
                min_obs = 2 if n_kfs <= 2 else 3
                ref_ids = ref.point_ids[self._valid_point_ids(ref.point_ids)]
                n_obs = self.store.point_rows(ref_ids, "n_observations") if ref_ids.size else np.zeros(0, np.int64)
                n_ref = int(np.count_nonzero(n_obs >= min_obs))
                if inliers >= cfg.keyframe_max_ref_ratio * n_ref:
                    return False  # condition 4
        if mapping_idle or frame.index >= self.last_kf_frame_index + cfg.keyframe_max_frames_idle:
            return True  # condition 2
        t0 = time.perf_counter()
        insert = self.on_mapping_busy()
        # the threaded runner playing as fast as possible holds tracking here until local mapping is free
        self._mapping_wait_ms = (time.perf_counter() - t0) * 1e3
        return insert

    # ---- V-C: relocalization ---------------------------------------------------------------------------

    def _relocalize(self, frame: Frame) -> bool:
        """ORB-SLAM Relocalization: BoW candidates -> BoW matches (>= 15) -> PnP in RANSAC (EPnP) ->
        motion-only BA -> guided search for more matches -> accepted with at least 50 inliers."""
        if self.place is None:
            return False
        bow = self._bow_of(frame)
        # candidates of every map, grouped in their own maps; only the active map's are tried (ORB-SLAM3
        # DetectRelocalizationCandidates(F, pMap): pKFi->GetMap() != pMap -> skipped)
        for kf_id, _ in self.place.relocalization_candidates(bow, self.atlas.best_neighbors):
            if not self.store.has_keyframe(kf_id):
                continue
            kf = self.store.get_keyframe(kf_id)
            if kf.bow is None:
                continue
            valid = self._valid_point_ids(kf.point_ids)
            matcher = self.cfg.matcher
            pairs = self.place.match(
                kf.features,
                kf.bow,
                frame.features,
                bow,
                matcher.ratio_relocalization,
                valid,
                None,
                max_distance=matcher.th_low,
                rotation_bins=matcher.rotation_bins,
            )
            if pairs.shape[0] < _RELOC_MIN_BOW_MATCHES:
                continue
            uv = frame.features.uv_undist_px[pairs[:, 1]].astype(np.float64)
            if not frame.camera.image_undistorted:
                # a fisheye keypoint enters EPnP as its bearing seen through K (ORB-SLAM3 solves PnP on bearings);
                # rays at or behind 90 degrees have no such pixel and are left out
                b = frame.features.bearing[pairs[:, 1]]
                ahead = b[:, 2] > 0
                pairs, b = pairs[ahead], b[ahead]
                if pairs.shape[0] < _RELOC_MIN_BOW_MATCHES:
                    continue
                uv = (b[:, :2] / b[:, 2:3]) @ frame.camera.K[:2, :2].T + frame.camera.K[:2, 2]
            xyz = np.stack([self.store.get_point(int(kf.point_ids[i])).xyz_w for i in pairs[:, 0]])
            ok, rvec, tvec, inliers = cv2.solvePnPRansac(
                xyz,
                uv,
                frame.camera.K,
                None,
                iterationsCount=300,
                reprojectionError=float(np.sqrt(self.cfg.chi2.mono)),
                confidence=0.99,
                flags=cv2.SOLVEPNP_EPNP,
            )
            if not ok or inliers is None or len(inliers) < _RELOC_MIN_PNP_INLIERS:
                continue
            T = np.eye(4)
            T[:3, :3] = cv2.Rodrigues(rvec)[0]
            T[:3, 3] = tvec.ravel()
            frame.point_ids[:] = -1
            sel = pairs[inliers.ravel()]
            frame.point_ids[sel[:, 1]] = kf.point_ids[sel[:, 0]]
            self._optimize_pose(frame, T)
            good = self._discard_outliers(frame)
            if good < _RELOC_MIN_PNP_INLIERS:
                continue
            # ORB-SLAM Relocalization: SearchByProjection(frame, kf, found, 10, TH_HIGH), then (3, 64)
            for radius, max_dist in ((10.0, matcher.th_high), (3.0, 64)):
                if good >= self.cfg.min_local_map_inliers_after_reloc:
                    break
                added = self._search_keyframe_points(frame, kf, radius, max_dist)
                if good + added >= self.cfg.min_local_map_inliers_after_reloc:
                    assert frame.T_c_w is not None
                    self._optimize_pose(frame, frame.T_c_w)
                    good = self._discard_outliers(frame)
            if good >= self.cfg.min_local_map_inliers_after_reloc:
                self.reference_kf_id = kf_id
                frame.ref_kf_id = kf_id
                log.info("relocalized frame %d against keyframe %d with %d inliers", frame.index, kf_id, good)
                return True
        frame.point_ids[:] = -1
        frame.T_c_w = None
        return False

    def _search_keyframe_points(self, frame: Frame, kf: KeyFrame, radius_px: float, max_distance: int) -> int:
        """ORB-SLAM SearchByProjection(Frame, KeyFrame): project the keyframe's points not matched yet with the
        frame's pose and match them around the projection (radius x scale of the predicted level)."""
        assert frame.T_c_w is not None
        found = {int(p) for p in frame.point_ids if p >= 0}
        pids = [int(p) for p in kf.point_ids if p >= 0 and int(p) not in found and self.store.has_point(int(p))]
        if not pids:
            return 0
        points = [self.store.get_point(p) for p in pids]
        feats = frame.features
        xyz = np.stack([p.xyz_w for p in points])
        uv, _, valid = project_points(frame.T_c_w, xyz, frame.camera)
        center = -frame.T_c_w[:3, :3].T @ frame.T_c_w[:3, 3]
        dist = np.linalg.norm(xyz - center, axis=1)
        d_min = np.array([p.d_min_m for p in points])
        d_max = np.array([p.d_max_m for p in points])
        ok = valid & (dist >= 0.8 * d_min) & (dist <= 1.2 * d_max)
        ok &= frame.bounds.contains(np.nan_to_num(uv, nan=-1e9))
        q = np.flatnonzero(ok)
        if q.size == 0:
            return 0
        level = predict_level(d_max[q], dist[q], feats.scale_factor, feats.n_levels)
        m = match_projected(
            feats,
            frame.point_ids >= 0,
            frame.bounds,
            uv[q],
            np.stack([points[i].descriptor for i in q]),
            radius_px * np.power(feats.scale_factor, level),
            level - 1,
            level + 1,
            max_distance,
            None,
            None,
            None,
        )
        frame.point_ids[m.feature] = np.array(pids, np.int64)[q[m.query]]
        return len(m)
