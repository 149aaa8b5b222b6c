"""Loop closing (ORB-SLAM sec. VII): detect loop candidates with the place recognizer, check their
consistency over three keyframes, then (ORB-SLAM3 sec. VI, LoopClosing::DetectCommonRegionsFromBoW, the default)
for the best three candidates pool BoW matches from the candidate and its covisible keyframes, Sim3 RANSAC,
guided matching, Sim3 optimisation and refined guided matching, keep the best, and verify it geometrically in
other keyframes (see ``loop_verification``; possibly over the next keyframes) -- or (ORB-SLAM2's ComputeSim3,
``geometric_verification: false``) compute and optimize the Sim3 on each candidate's BoW matches and require
enough matches -- then correct the loop (Sim3 propagation, loop fusion, essential graph).

The same detection is the Atlas' merge detection (ORB-SLAM3 sec. III-A, LoopClosing::NewDetectCommonRegions): a
common region in the active map is a loop; one in another map of the Atlas is a merge. A merge candidate goes
through the same common-region search (``_common_region`` with the candidate's map as the window's side) and the
same verification in the current keyframe's covisibles and the next keyframes (its own pending hypothesis, as
ORB-SLAM3's mnMergeNumCoincidences), without the loop's temporal consistency (ORB-SLAM3 has none) and without the
loop's rotation bound (two maps' world frames are unrelated). An accepted merge is ``LoopDetection.merge``.

Detection and correction are two steps, as in ORB-SLAM (DetectLoop/ComputeSim3, then CorrectLoop):
``LoopCloser.detect(kf)`` runs after local mapping has processed ``kf`` and *while local mapping goes on* (it reads
the map under its read lock and pins the keyframes it uses, slamkit/pipeline/keyframe_pins.py, so culling leaves
them); only an accepted loop's ``LoopCloser.correct(detection)`` needs local mapping stopped, which the runner
does (ORB-SLAM CorrectLoop: RequestStop). ``step(kf)`` is the two in a row. Every decision is recorded in a
``LoopOutcome`` so a user can see why a loop was or was not closed.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slamkit.features import Observations
from slamkit.geometry.sim3 import Sim3
from slamkit.geometry.sim3_ransac import Projection, ransac_sim3
from slamkit.interfaces import Camera, MapStore, Optimizer, PlaceRecognizer
from slamkit.map.atlas import Atlas
from slamkit.map.entities import KeyFrame
from slamkit.map.mapfile_contents import check_contents, read_map_contents
from slamkit.pipeline.bundle import BundleSnapshot, intrinsics_of, problem_camera, run_bundle
from slamkit.pipeline.config import LoopClosingConfig
from slamkit.pipeline.fusion import fuse_points, replace_point
from slamkit.pipeline.global_ba import GlobalBAOutcome, commit_global_ba, optimize_global_ba, snapshot_global_ba
from slamkit.pipeline.keyframe_pins import KeyFramePins
from slamkit.pipeline.loop_correction import (
    LoopCorrection,
    MapMove,
    apply_essential_graph,
    essential_graph_move,
    essential_graph_problem,
    loop_correction_move,
    propagate_loop_sim3,
    read_then_write,
    sim3_of_pose,
    write_map_move,
)
from slamkit.pipeline.loop_verification import (
    KeyframeCheck,
    PendingLoop,
    PendingStep,
    VerificationThresholds,
    WindowProjection,
    advance_pending,
    check_covisibles,
    check_keyframe,
    common_region_keyframes,
    loop_rotation_deg,
    loop_window,
    points_of,
    project_window,
    verification_window,
)
from slamkit.pipeline.map_merging import (
    apply_moved_map,
    import_map,
    merge_essential_graph_problem,
    moved_map,
    rooted_at,
    welding_bundle,
    welding_window,
    window_points,
)
from slamkit.pipeline.map_points import refresh_points, unique_point_ids
from slamkit.pipeline.outcomes import LoopOutcome
from slamkit.problems import Sim3Problem

log = logging.getLogger("slamkit.loop")

I64 = NDArray[np.int64]


def pending_record(pending: PendingLoop, step: PendingStep) -> dict[str, object]:
    """What loops.json says of a carried-over hypothesis (loop or merge) after this keyframe's check."""
    return {
        "state": step.state,
        "check": step.check.as_dict(),
        "coincidences": pending.coincidences,
        "misses": pending.misses,
    }


@dataclass(frozen=True)
class AcceptedLoop:
    """A loop detection accepted: the loop keyframe, S_cw the current keyframe's corrected Sim3 pose (world to
    camera) and matches (current keyframe's feature -> loop map point id)."""

    loop_kf_id: int
    S_cw: Sim3
    matches: dict[int, int]


@dataclass(frozen=True)
class AcceptedMerge:
    """A merge detection accepted (ORB-SLAM3 mbMergeDetected): the matched keyframe ``merge_kf_id`` in the map
    ``map_id`` (not the active one), S_cw the current keyframe's Sim3 pose in that map's world frame (world ->
    camera) and matches (current keyframe's feature -> matched map's point id)."""

    merge_kf_id: int
    map_id: int
    S_cw: Sim3
    matches: dict[int, int]


@dataclass(frozen=True)
class MapMerge:
    """What a merge did to the maps, as it happens (``LoopCloser.on_merge``): the active map ``into_map_id`` (whose
    keyframes ``moved_kf_ids`` were moved by ``G``, x_new = G x_old, into the other map's world frame) absorbs the map
    ``merged_map_id``; ``kf_id`` / ``matched_kf_id`` the keyframes of the common region."""

    kf_id: int
    matched_kf_id: int
    merged_map_id: int
    into_map_id: int
    moved_kf_ids: frozenset[int]
    G: Sim3


@dataclass
class LoopDetection:
    """What :meth:`LoopCloser.detect` did at one keyframe: its outcome so far, the accepted loop (None: no loop to
    correct) and the accepted merge (None: no merge; a keyframe has one or the other). pinned: the keyframe of an
    accepted loop or merge and the loop keyframe are still pinned (until corrected or released)."""

    kf: KeyFrame
    outcome: LoopOutcome
    loop: AcceptedLoop | None
    pinned: bool = False
    merge: AcceptedMerge | None = None


@dataclass
class _Hypothesis:
    """A common region found from one BoW candidate (ORB-SLAM3 DetectCommonRegionsFromBoW): the matched keyframe,
    S_cw the current keyframe's pose in the loop side's frame, the refined matches (current feature -> loop point
    id), the verification window's point ids, and the candidate's record in LoopOutcome.tried."""

    matched_kf_id: int
    S_cw: Sim3
    matches: dict[int, int]
    window: list[int]
    info: dict[str, object]


def _pinhole(K: NDArray[np.float64], xyz_c: NDArray[np.float64]) -> NDArray[np.float64]:
    """(N, 2) px: camera-frame points (N, 3), z > 0, through the pinhole K (3, 3)."""
    return np.stack([K[0, 0] * xyz_c[:, 0] / xyz_c[:, 2] + K[0, 2], K[1, 1] * xyz_c[:, 1] / xyz_c[:, 2] + K[1, 2]], 1)


def _image_projection(camera: Camera) -> Projection | None:
    """The Sim3 RANSAC's projection into ``camera``'s pipeline image: None (the pinhole K) for an undistorted pinhole
    image, else the camera's own model (a fisheye camera's raw pixels; ORB-SLAM3 Sim3Solver: mpCamera->project)."""
    return None if camera.image_undistorted else camera.project_image


def _project_camera(camera: Camera, xyz_c: NDArray[np.float64]) -> NDArray[np.float64]:
    """(N, 2) px: camera-frame points (N, 3), z > 0, in ``camera``'s pipeline image (the pinhole K for an undistorted
    image, else the camera's model: ORB-SLAM3 pKF->mpCamera->project)."""
    if camera.image_undistorted:
        return _pinhole(camera.K, xyz_c)
    uv, _ = camera.project_image(xyz_c)
    return np.asarray(uv, np.float64)


def _sim3_cameras(camera_1: Camera, camera_2: Camera) -> dict[str, Any]:
    """The camera-model fields of a Sim3Problem between keyframes seen by ``camera_1`` and ``camera_2`` (ORB-SLAM3
    OptimizeSim3: vSim3->pCamera1 / pCamera2)."""
    c1, c2 = problem_camera(camera_1), problem_camera(camera_2)
    return {
        "camera_model1": c1["camera_model"],
        "distortion1": c1["distortion"],
        "camera_model2": c2["camera_model"],
        "distortion2": c2["distortion"],
    }


def _camera_1(features: Observations, idx: I64) -> NDArray[np.bool_]:
    """(M,) bool: which keypoints ``idx`` (M,) are camera 1's. Loop closing's Sim3 (ORB-SLAM3 Sim3Solver and
    OptimizeSim3 take a point's keypoint in a keyframe as get<0> of GetIndexInKeyFrame, its camera-1 keypoint, and
    project with mpCamera) works on camera 1's keypoints of a two-camera record; all keypoints of a one-camera one."""
    if not features.two_cameras:
        return np.ones(idx.shape[0], bool)
    return np.asarray(idx < features.n_left)


@dataclass
class _ConsistentGroup:
    members: set[int]
    count: int


class LoopCloser:
    """Loop detection and correction over the map (deterministic given the rng)."""

    def __init__(
        self,
        cfg: LoopClosingConfig,
        atlas: Atlas,
        optimizer: Optimizer,
        place: PlaceRecognizer,
        rng: np.random.Generator,
        pins: KeyFramePins | None = None,
    ) -> None:
        """pins: the keyframes loop closing is using, which local mapping's culling must leave (give local mapping
        the same object)."""
        self.cfg = cfg
        self.pins = pins if pins is not None else KeyFramePins()
        self.atlas = atlas  # the maps; loop closing works on the active one (``store``)
        self.optimizer = optimizer
        self.place = place
        self.rng = rng
        self.last_loop_kf_id = -(10**9)
        self._groups: list[_ConsistentGroup] = []
        self._pending: PendingLoop | None = None
        self._pending_merge: tuple[int, PendingLoop] | None = None  # (the matched map's id, the hypothesis)
        self.loops: list[LoopOutcome] = []
        self.merges: list[LoopOutcome] = []
        #: set by a runner: called under the active map's write lock when a merge moves the active map into another
        #: map's frame, before the other map's entities come in (the trajectory recorder rescales the frames recorded
        #: relative to the moved keyframes; the runner fires slamkit_maps_merged)
        self.on_merge: Callable[[MapMerge], None] | None = None
        self.global_bas: list[GlobalBAOutcome] = []
        self.global_ba_error: BaseException | None = None
        #: set by a threaded runner: a context manager parking local mapping (then the global BA runs in its own
        #: thread and parks local mapping only to write its result); None: the global BA runs in line
        self.park_mapping: Callable[[], AbstractContextManager[None]] | None = None
        self._gba_thread: threading.Thread | None = None
        self._gba_abort: threading.Event | None = None
        self._thresholds = VerificationThresholds(
            cfg.verify_search_radius_px,
            cfg.verify_min_matches,
            int(cfg.matcher.th_low * cfg.common_regions_hamming_ratio),
        )

    @property
    def store(self) -> MapStore:
        """The active map of the Atlas."""
        return self.atlas.active

    def _neighbors(self, kf_id: int, n: int) -> list[int]:
        return self.store.covisibility.best_neighbors(kf_id, n) if kf_id in self.store.covisibility else []

    def step(self, kf: KeyFrame) -> LoopOutcome:
        """Detection, then the merge or the correction of a loop it accepted (what the sequential runner does)."""
        detection = self.detect(kf)
        if detection.merge is not None:
            return self.merge(detection)
        return self.correct(detection) if detection.loop is not None else detection.outcome

    # ---- detection (local mapping goes on meanwhile) ------------------------------------------------------

    def detect(self, kf: KeyFrame) -> LoopDetection:
        """Look for a loop at ``kf`` (VII-A/B and ORB-SLAM3's verification) without stopping local mapping.

        The map is read under its read lock, in phases (candidates and consistency; per candidate its BoW matches,
        then, after the Sim3 RANSAC and optimization done without the lock, the guided search and verification);
        the keyframes in use are pinned (``self.pins``) so local mapping's culling leaves them, and a point or
        keyframe erased between phases is skipped. An accepted loop keeps ``kf`` and the loop keyframe pinned until
        :meth:`correct` (or :meth:`release`). Ends by adding ``kf`` to the place recognizer's database."""
        out = LoopOutcome(kf.id)
        t0 = time.perf_counter()
        with self.store.read():
            if kf.bow is None or not self.store.has_keyframe(kf.id):
                out.reason = "keyframe has no bag of words or was culled"
                return LoopDetection(kf, out, None)
            self.pins.pin(kf.id)
        loop: AcceptedLoop | None = None
        merge: AcceptedMerge | None = None
        try:
            merge = self._find_merge(kf, out)
            if merge is None or not self.cfg.merge_maps:
                # ORB-SLAM3 LoopClosing::Run: a detected merge comes first, the loop search waits for the merged map
                loop = self._find_loop(kf, out, t0)
        finally:
            with self.store.read():
                if self.store.has_keyframe(kf.id) and kf.bow is not None:
                    self.place.add(kf.id, kf.bow)
        if merge is not None:
            self._pending_merge = None
            out.merge_kf_id, out.merge_map_id = merge.merge_kf_id, merge.map_id
            out.merge_matches, out.merge_scale = len(merge.matches), merge.S_cw.s
            log.info(
                "keyframe %d: merge with map %d detected at its keyframe %d, %d matches, scale %.3f%s",
                kf.id,
                merge.map_id,
                merge.merge_kf_id,
                len(merge.matches),
                merge.S_cw.s,
                "" if self.cfg.merge_maps else " (not merged: pipeline.loop_closing.merge_maps is false)",
            )
            if not self.cfg.merge_maps:
                merge = None
        if loop is not None:
            self._pending = None
            out.loop_kf_id, out.matches, out.scale = loop.loop_kf_id, len(loop.matches), loop.S_cw.s
        pinned = loop is not None or merge is not None
        if not pinned:
            self.pins.unpin(kf.id)
        return LoopDetection(kf, out, loop, pinned=pinned, merge=merge)

    def _find_loop(self, kf: KeyFrame, out: LoopOutcome, t0: float) -> AcceptedLoop | None:
        """The accepted loop at ``kf`` (pinned), or None with ``out.reason`` saying why not."""
        assert kf.bow is not None
        if not self.cfg.enabled:
            out.reason = "loop closing disabled"
            return None
        with self.store.read():
            if self._pending is not None:
                loop = self._check_pending(kf, out)
                if loop is not None:
                    return loop
                if self._pending is not None and self._pending.misses == 0:
                    # ORB-SLAM3: a keyframe that confirmed the pending loop is not searched for another one
                    out.reason = out.reason or "pending loop confirmed; more keyframes must agree"
                    return None
            if kf.id < self.last_loop_kf_id + self.cfg.min_keyframes_between_loops or (
                self.store.n_keyframes() <= self.cfg.min_keyframes_between_loops
            ):
                out.reason = "too close to the map's start or to the last loop"
                return None
            out.consistent = self._detect(kf, out)
            self.pins.pin(*out.consistent)  # ORB-SLAM DetectLoop: SetNotErase on the consistent candidates
        out.timings_ms["detect_ms"] = (time.perf_counter() - t0) * 1e3
        if not out.consistent:
            return None
        t1 = time.perf_counter()
        try:
            loop = self._common_regions(kf, out) if self.cfg.geometric_verification else self._compute_sim3(kf, out)
        finally:
            self.pins.unpin(*out.consistent)  # ORB-SLAM: SetErase on those not chosen
        out.timings_ms["sim3_ms"] = (time.perf_counter() - t1) * 1e3
        if loop is None:
            out.reason = out.reason or "no candidate passed the Sim3 checks"
        return loop

    def _accept(self, loop_kf_id: int, S_cw: Sim3, matches: dict[int, int]) -> AcceptedLoop:
        """An accepted loop, its loop keyframe pinned until the correction (called under the read lock)."""
        self.pins.pin(loop_kf_id)
        return AcceptedLoop(loop_kf_id, S_cw, matches)

    # ---- correction (local mapping parked) ------------------------------------------------------------------

    def correct(self, detection: LoopDetection) -> LoopOutcome:
        """Correct the loop ``detection`` accepted (VII-C/D); the caller keeps local mapping stopped meanwhile
        (ORB-SLAM CorrectLoop: RequestStop). Releases the keyframes detection pinned."""
        loop = detection.loop
        if loop is None:
            raise ValueError(f"keyframe {detection.outcome.kf_id}: detection accepted no loop to correct")
        kf, out = detection.kf, detection.outcome
        try:
            self.abort_global_ba()
            t2 = time.perf_counter()
            self._correct(kf, loop.loop_kf_id, loop.S_cw, loop.matches, out)
            out.timings_ms["correction_ms"] = (time.perf_counter() - t2) * 1e3
            self.last_loop_kf_id = kf.id
            self.loops.append(out)
        finally:
            self.release(detection)
        log.info(
            "loop closed: keyframe %d <-> %d, %d matches, scale %.3f, %d essential-graph edges",
            kf.id,
            loop.loop_kf_id,
            out.matches,
            out.scale,
            out.essential_graph_edges,
        )
        return out

    def release(self, detection: LoopDetection) -> None:
        """Unpin the keyframes of an accepted loop (done by :meth:`correct`; call it for a loop that will not be
        corrected, e.g. the run stops). Idempotent."""
        if detection.pinned:
            self.pins.unpin(detection.kf.id, *([detection.loop.loop_kf_id] if detection.loop is not None else []))
            detection.pinned = False

    # ---- ORB-SLAM3 sec. III-B: map merging (local mapping parked) -------------------------------------------

    def merge(self, detection: LoopDetection, global_ba_stopped: bool = False) -> LoopOutcome:
        """Merge the map ``detection`` found (ORB-SLAM3 MergeLocal, slamkit/pipeline/map_merging.py) into the
        active map; the caller keeps local mapping stopped meanwhile (ORB-SLAM3: RequestStop). Tracking goes on: it
        waits only while the map is written (the rigid move, the import and the fusion, then the welding BA's and the
        essential graph's results). A global BA follows only when one was running and stopped for the merge (here,
        or by the caller: ``global_ba_stopped``), as ORB-SLAM3's bRelaunchBA, unless ``merge_global_ba`` asks for one
        after every merge. Releases the keyframe detection pinned."""
        merge = detection.merge
        if merge is None:
            raise ValueError(f"keyframe {detection.outcome.kf_id}: detection accepted no merge")
        kf, out = detection.kf, detection.outcome
        try:
            relaunch = self.abort_global_ba() or global_ba_stopped
            t0 = time.perf_counter()
            self._merge(kf, merge, out, relaunch)
            out.timings_ms["merge_ms"] = (time.perf_counter() - t0) * 1e3
            self.last_loop_kf_id = kf.id
            self._pending = None
            self._groups = []
            self.merges.append(out)
        finally:
            self.release(detection)
        log.info(
            "maps merged: map %d into the active map %d (keyframe %d <-> %d, %d matches, scale %.3f), %d keyframes "
            "imported, %.0f ms (the map locked for %.0f ms at most)",
            merge.map_id,
            self.atlas.active_id,
            kf.id,
            merge.merge_kf_id,
            len(merge.matches),
            merge.S_cw.s,
            out.merge_imported_keyframes,
            out.timings_ms.get("merge_ms", 0.0),
            max((v for k, v in out.timings_ms.items() if k.startswith("merge_locked")), default=0.0),
        )
        return out

    def _merge(self, kf: KeyFrame, merge: AcceptedMerge, out: LoopOutcome, relaunch_global_ba: bool) -> None:
        cfg = self.cfg
        store = self.store
        other = self.atlas.get(merge.map_id)  # not the active map: nobody changes it
        t_prepare = time.perf_counter()
        n_window, tries = cfg.merge_window_keyframes, cfg.merge_window_max_tries
        # ORB-SLAM3 MergeLocal: the windows of the two maps, before anything moves
        merge_window = welding_window(other, merge.merge_kf_id, n_window, tries)
        merge_points = window_points(other, merge_window)
        # prepared before the write lock (ORB-SLAM3 MergeLocal computes the corrected poses and positions first, then
        # takes the map mutex to set them): the other map's contents with its tree re-rooted at the matched keyframe,
        # and where the move takes the active map (local mapping is parked, tracking adds nothing: they stay valid)
        contents = rooted_at(read_map_contents(other), merge.merge_kf_id)
        check_contents(contents, store.ids)  # MapStore.add_contents's check, done here instead of under the lock
        with store.read():
            # x_other = G x_active: the current keyframe's camera sees the same point as T_c_w x_active and S_cw x_other
            G = merge.S_cw.inverse() @ sim3_of_pose(kf.T_c_w)
            moved_to = moved_map(store, G)
        out.timings_ms["merge_prepare_ms"] = (time.perf_counter() - t_prepare) * 1e3
        t_lock = time.perf_counter()
        with store.write():
            store.update_connections(kf.id)  # ORB-SLAM3: mpCurrentKF->UpdateConnections()
            current_window = welding_window(store, kf.id, n_window, tries)
            moved = frozenset(store.keyframe_ids())
            apply_moved_map(store, moved_to, G)
            if self.on_merge is not None:
                self.on_merge(MapMerge(kf.id, merge.merge_kf_id, merge.map_id, self.atlas.active_id, moved, G))
            before_links = {k: set(store.covisibility.neighbors(k)) for k in current_window}
            imported = import_map(store, contents, kf.id, merge.matches, checked=True)
            self.atlas.absorb(merge.map_id)
            fused = 0
            for k in current_window:
                if store.has_keyframe(k):
                    fused += fuse_points(
                        store,
                        store.get_keyframe(k),
                        merge_points,
                        cfg.loop_fuse_radius_px,
                        incoming_wins=True,
                        max_distance=cfg.matcher.th_low,
                        chi2_gate=cfg.chi2.fuse_mono,
                    )
            for k in [*current_window, *merge_window]:
                if store.has_keyframe(k):
                    store.update_connections(k)
            new_links = {
                k: set(store.covisibility.neighbors(k)) - before_links.get(k, set()) - set(current_window)
                for k in current_window
                if store.has_keyframe(k)
            }
            new_links.setdefault(kf.id, set()).add(merge.merge_kf_id)
            store.add_loop_edge(kf.id, merge.merge_kf_id)
            store.bump_epoch()
            before = {k: sim3_of_pose(store.get_keyframe(k).T_c_w) for k in store.keyframe_ids() if k not in imported}
        out.timings_ms["merge_locked_weld_ms"] = (time.perf_counter() - t_lock) * 1e3
        out.merge_imported_keyframes = len(imported)
        out.merge_fused = fused
        out.merge_transform = G.matrix().tolist()
        # the welding BA: snapshot under the read lock, optimized without it, committed under the write lock
        t_ba = time.perf_counter()
        with store.read():
            snap = welding_bundle(
                store,
                current_window,
                merge_window,
                cfg.merge_ba_iterations_first,
                cfg.merge_ba_iterations_second,
                cfg.chi2.mono,
                cfg.chi2.stereo,
            )
        if snap is not None:
            result = run_bundle(store, self.optimizer, snap)
            out.merge_ba_outliers = int(result.outlier.sum())
            with store.write():
                refresh_points(store, snap.point_ids.tolist(), normals=True, descriptors=False)
        out.timings_ms["merge_welding_ba_ms"] = (time.perf_counter() - t_ba) * 1e3
        if cfg.merge_essential_graph:
            t_eg = time.perf_counter()
            with store.read():
                fixed = set(imported) | set(current_window) | set(merge_window)
                problem, eg_kf_ids = merge_essential_graph_problem(store, fixed, before, new_links, cfg.theta_min)
            if not problem.fixed.all():
                result_eg = self.optimizer.optimize_essential_graph(problem)
                t_write = time.perf_counter()
                with store.write():
                    apply_essential_graph(store, problem, result_eg, eg_kf_ids)
                    store.bump_epoch()
                out.timings_ms["merge_locked_essential_graph_ms"] = (time.perf_counter() - t_write) * 1e3
                out.essential_graph_edges = int(problem.edge_i.shape[0])
            out.timings_ms["merge_essential_graph_ms"] = (time.perf_counter() - t_eg) * 1e3
        # ORB-SLAM3 MergeLocal: "if(bRelaunchBA && (!pCurrentMap->isImuInitialized() || ...))" -> a global BA on the
        # merged map only in place of one the merge stopped (a visual map is never IMU-initialised)
        if cfg.global_ba and (relaunch_global_ba or cfg.merge_global_ba):
            self.start_global_ba(kf.id)

    # ---- VII-A: detection ----------------------------------------------------------------------------

    def _detect(self, kf: KeyFrame, out: LoopOutcome) -> list[int]:
        """Candidates scoring above s_min (the lowest score against covisible neighbours with weight >= 30),
        kept only when consistent over ``consistency_detections`` consecutive keyframes (ORB-SLAM2), or all of
        them when the geometric verification is on (ORB-SLAM3)."""
        assert kf.bow is not None
        cfg = self.cfg
        cov = self.store.covisibility
        min_score = self._min_score(kf)
        # the other maps' keyframes are left out like the connected ones: a loop is searched in the active map only
        # (ORB-SLAM3 DetectLoopCandidates: "it must be in the same map"; the other maps' are merge candidates)
        other_maps = self.atlas.keyframes_outside_active()
        connected = {kf.id, *cov.neighbors(kf.id)} | other_maps
        candidates = [
            k
            for k, _ in self.place.loop_candidates(kf.bow, connected, min_score, self._neighbors)
            if self.store.has_keyframe(k)
        ]
        out.candidates = candidates
        if not candidates:
            self._groups = []
            out.reason = f"no candidate above s_min = {min_score:.3f}"
            return []
        new_groups: list[_ConsistentGroup] = []
        consistent: list[int] = []
        for cand in candidates:
            members = {cand, *cov.neighbors(cand)}
            counts = [g.count + 1 for g in self._groups if g.members & members]
            count = max(counts) if counts else 0
            new_groups.append(_ConsistentGroup(members, count))
            if count >= cfg.consistency_detections - 1 and cand not in consistent:
                consistent.append(cand)
        self._groups = new_groups
        # The temporal consistency holds with the geometric verification too (issue 14): a candidate goes on to
        # the Sim3 only once three consecutive keyframes found it or its covisible group; ORB-SLAM3's checks in
        # the covisible and next keyframes come on top (docs/pipeline.md).
        if not consistent:
            out.reason = f"{len(candidates)} candidate(s), none consistent over {cfg.consistency_detections} keyframes"
        return consistent

    def _min_score(self, kf: KeyFrame) -> float:
        """VII-A's s_min: the lowest BoW score of ``kf`` against its covisible neighbours with weight >= 30 (all of
        them when none is that strong; 0 without neighbours). Called under the read lock."""
        assert kf.bow is not None
        cov = self.store.covisibility
        strong = cov.neighbors(kf.id, self.cfg.candidate_min_covisible_weight) or cov.neighbors(kf.id)
        scores = [self.place.score(kf.bow, b) for n in strong if (b := self.store.get_keyframe(n).bow) is not None]
        return min(scores) if scores else 0.0

    # ---- ORB-SLAM3 sec. III-A: merge detection (a common region in another map of the Atlas) ---------------

    def _find_merge(self, kf: KeyFrame, out: LoopOutcome) -> AcceptedMerge | None:
        """ORB-SLAM3 NewDetectCommonRegions' merge half: a pending merge is checked in ``kf`` first (accepted after
        ``verify_coincidences`` agreeing keyframes); else, once the active map has more than
        ``min_keyframes_between_loops`` keyframes, the best ``n_best_candidates`` place-recognition candidates in
        other maps (DetectNBestCandidates) each give a common-region hypothesis (``_common_region`` in the
        candidate's map), and the one with the most refined matches is verified in the current keyframe's covisible
        keyframes (``_verify``). Records in ``out.merge_candidates`` / ``merge_tried`` / ``merge_pending``."""
        assert kf.bow is not None
        cfg = self.cfg
        if not cfg.enabled:
            return None
        with self.store.read():
            if self._pending_merge is not None:
                merge = self._check_pending_merge(kf, out)
                if merge is not None or (self._pending_merge is not None and self._pending_merge[1].misses == 0):
                    return merge  # accepted, or confirmed by this keyframe: more keyframes must agree
            if self.store.n_keyframes() <= cfg.min_keyframes_between_loops:
                return None  # ORB-SLAM3 NewDetectCommonRegions: no detection in a map of fewer than 12 keyframes
            other_maps = self.atlas.keyframes_outside_active()
            if not other_maps:
                return None
            active = set(self.store.keyframe_ids()) | {kf.id}
            ranked = self.place.loop_candidates(kf.bow, active, self._min_score(kf), self.atlas.best_neighbors)
            out.merge_candidates = [k for k, _ in ranked if k in other_maps][: cfg.n_best_candidates]
        best: tuple[_Hypothesis, int] | None = None
        for cand_id in out.merge_candidates:
            map_id = self.atlas.map_of(cand_id)
            info: dict[str, object] = {"candidate": cand_id, "map": map_id}
            out.merge_tried.append(info)
            if map_id is None or map_id == self.atlas.active_id:
                info["rejected"] = "no longer in another map"
                continue
            hyp = self._common_region(kf, cand_id, info, self.atlas.get(map_id))
            if hyp is not None and (best is None or len(hyp.matches) > len(best[0].matches)):
                best = (hyp, map_id)
        if best is None:
            return None
        hyp, map_id = best
        for info in out.merge_tried:
            if info is not hyp.info and "rejected" not in info:
                info["rejected"] = "another candidate has more refined matches (ORB-SLAM3: best of the candidates)"
        with self.store.read():
            if not self.store.has_keyframe(kf.id):
                hyp.info["rejected"] = "culled before the verification"
                return None
            return self._verify_merge(kf, map_id, hyp)

    def _verify_merge(self, kf: KeyFrame, map_id: int, hyp: _Hypothesis) -> AcceptedMerge | None:
        """The verification of a merge hypothesis (as a loop's in ``_verify``, without the rotation bound): accepted,
        pending (``self._pending_merge``) or rejected. Called under the read lock."""
        cfg = self.cfg
        merge_store = self.atlas.get(map_id)
        own, _ = check_keyframe(merge_store, kf, hyp.S_cw, hyp.window, self._thresholds)
        checks: list[KeyframeCheck] = [own]
        if own.agrees:
            checks += check_covisibles(
                self.store,
                kf,
                hyp.S_cw,
                hyp.window,
                self._thresholds,
                cfg.verify_covisible_keyframes,
                cfg.verify_coincidences,
                window_store=merge_store,
            )
        agreeing = sum(c.agrees for c in checks[1:])
        hyp.info["verification"] = [c.as_dict() for c in checks]
        hyp.info["agreeing"] = agreeing
        if not own.agrees:
            hyp.info["rejected"] = f"verification: the current keyframe disagrees ({own.why})"
            return None
        if agreeing >= cfg.verify_coincidences:
            return AcceptedMerge(hyp.matched_kf_id, map_id, hyp.S_cw, hyp.matches)
        if agreeing == 0:
            hyp.info["rejected"] = "verification: no covisible keyframe agrees"
            return None
        pending = PendingLoop(hyp.matched_kf_id, kf.id, kf.T_c_w.copy(), hyp.S_cw, hyp.window, agreeing, 0, hyp.matches)
        self._pending_merge = (map_id, pending)
        hyp.info["rejected"] = (
            f"verification: {agreeing} of {cfg.verify_coincidences} keyframes agree; pending for the next keyframes"
        )
        return None

    def _check_pending_merge(self, kf: KeyFrame, out: LoopOutcome) -> AcceptedMerge | None:
        """A pending merge checked in a new keyframe, as a pending loop (``_check_pending``; ORB-SLAM3
        mnMergeNumCoincidences / mnMergeNumNotFound). Called under the read lock."""
        assert self._pending_merge is not None
        map_id, pending = self._pending_merge
        if map_id not in self.atlas.map_ids() or map_id == self.atlas.active_id:
            self._pending_merge = None
            out.merge_pending = {"merge_kf": pending.loop_kf_id, "state": "dropped", "why": "the map is gone"}
            return None
        merge_store = self.atlas.get(map_id)
        if not merge_store.has_keyframe(pending.loop_kf_id):
            self._pending_merge = None
            out.merge_pending = {"merge_kf": pending.loop_kf_id, "state": "dropped", "why": "merge keyframe gone"}
            return None
        cfg = self.cfg

        def refine(k: KeyFrame, S_k_w: Sim3, proj: WindowProjection) -> str:
            return self._refine_hypothesis(k, merge_store, pending.loop_kf_id, S_k_w, proj)

        step = advance_pending(
            self.store,
            pending,
            kf,
            self._thresholds,
            cfg.verify_coincidences,
            cfg.verify_max_misses,
            refine,
            window_store=merge_store,
        )
        out.merge_pending = {"merge_kf": pending.loop_kf_id, "map": map_id, **pending_record(pending, step)}
        if step.state == "dropped":
            self._pending_merge = None
        if step.state == "accepted":
            return AcceptedMerge(pending.loop_kf_id, map_id, step.S_k_w, step.matches)
        return None

    # ---- VII-B: Sim3 -----------------------------------------------------------------------------------

    def _points_c(self, kf: KeyFrame, feats: I64) -> NDArray[np.float64]:
        xyz = np.stack([self.store.get_point(int(kf.point_ids[i])).xyz_w for i in feats])
        return np.asarray(xyz @ kf.T_c_w[:3, :3].T + kf.T_c_w[:3, 3])

    def _compute_sim3(self, kf: KeyFrame, out: LoopOutcome) -> AcceptedLoop | None:
        """For each consistent candidate: BoW matches, Sim3 RANSAC, Sim3 optimization, then a guided search
        of the candidate's neighbourhood points; the first candidate with enough matches is the loop.

        The map is read under the read lock before and after the RANSAC and optimization, which run on copied
        arrays without it; a candidate or point erased in between is skipped."""
        cfg = self.cfg
        store = self.store
        assert kf.bow is not None
        for cand_id in out.consistent:
            info: dict[str, object] = {"candidate": cand_id}
            out.tried.append(info)
            with store.read():
                if not store.has_keyframe(cand_id) or not store.has_keyframe(kf.id):
                    info["rejected"] = "culled"
                    continue
                cand = store.get_keyframe(cand_id)
                if cand.bow is None:
                    info["rejected"] = "no bag of words"
                    continue
                valid2 = store.has_points(cand.point_ids)
                pairs = self.place.match(
                    kf.features,
                    kf.bow,
                    cand.features,
                    cand.bow,
                    cfg.matcher.ratio_loop,
                    store.has_points(kf.point_ids),
                    valid2,
                    max_distance=cfg.matcher.th_low,
                    rotation_bins=cfg.matcher.rotation_bins,
                )
                info["bow_matches"] = int(pairs.shape[0])
                if pairs.shape[0] < cfg.sim3_min_bow_matches:
                    info["rejected"] = f"{pairs.shape[0]} BoW matches < {cfg.sim3_min_bow_matches}"
                    continue
                i1, i2 = pairs[:, 0], pairs[:, 1]
                left = _camera_1(kf.features, i1) & _camera_1(cand.features, i2)
                i1, i2 = i1[left], i2[left]
                if i1.shape[0] < cfg.sim3_min_bow_matches:
                    info["rejected"] = f"{i1.shape[0]} BoW matches in camera 1 < {cfg.sim3_min_bow_matches}"
                    continue
                xyz1, xyz2 = self._points_c(kf, i1), self._points_c(cand, i2)
                loop_pids = cand.point_ids[i2].copy()
            uv1 = kf.features.uv_undist_px[i1].astype(np.float64)
            uv2 = cand.features.uv_undist_px[i2].astype(np.float64)
            s1, s2 = kf.features.level_sigma2()[i1], cand.features.level_sigma2()[i2]
            ransac = ransac_sim3(
                xyz1,
                xyz2,
                uv1,
                uv2,
                kf.camera.K,
                cand.camera.K,
                s1,
                s2,
                self.rng,
                fix_scale=kf.features.bf > 0.0,
                probability=cfg.sim3_ransac_probability,
                min_inliers=cfg.sim3_ransac_min_inliers,
                max_iterations=cfg.sim3_ransac_max_iterations,
                chi2=cfg.chi2.sim3_ransac,
                project1=_image_projection(kf.camera),
                project2=_image_projection(cand.camera),
            )
            info["ransac_inliers"] = int(ransac.inliers.sum())
            if ransac.S_12 is None:
                info["rejected"] = "Sim3 RANSAC found no hypothesis"
                continue
            problem = Sim3Problem(
                S_12_init=ransac.S_12.matrix(),
                xyz1_c1=xyz1,
                xyz2_c2=xyz2,
                uv1_px=uv1,
                uv2_px=uv2,
                level1=kf.features.level[i1].astype(np.int64),
                level2=cand.features.level[i2].astype(np.int64),
                intrinsics1=intrinsics_of(kf.camera.K),
                intrinsics2=intrinsics_of(cand.camera.K),
                scale_factor=kf.features.scale_factor,
                chi2=cfg.chi2.sim3,
                fix_scale=kf.features.bf > 0.0,  # stereo/RGB-D: scale observable (ORB-SLAM2 mbFixScale)
                **_sim3_cameras(kf.camera, cand.camera),
            )
            opt = self.optimizer.optimize_sim3(problem)
            info["optimized_inliers"] = int(opt.inliers.sum())
            if opt.inliers.sum() < cfg.min_inliers_after_sim3_opt:
                info["rejected"] = f"{int(opt.inliers.sum())} inliers after Sim3 optimization"
                continue
            with store.read():
                if not store.has_keyframe(cand_id) or not store.has_keyframe(kf.id):
                    info["rejected"] = "culled during the Sim3 optimization"
                    continue
                S_12 = Sim3.from_matrix(opt.S_12)
                S_cw = S_12 @ sim3_of_pose(cand.T_c_w)
                inlier_pids = loop_pids[opt.inliers]
                alive = store.has_points(inlier_pids)
                matches = {int(a): int(p) for a, p in zip(i1[opt.inliers][alive], inlier_pids[alive], strict=True)}
                window = loop_window(store, cand_id)
                matches.update(self._search_loop_points(kf, S_cw, window, matches))
                info["loop_matches"] = len(matches)
                info["scale"] = S_12.s
                if len(matches) < cfg.min_loop_matches:
                    info["rejected"] = f"{len(matches)} matches < {cfg.min_loop_matches}"
                    continue
                return self._accept(cand_id, S_cw, matches)
        return None

    def _search_loop_points(
        self, kf: KeyFrame, S_cw: Sim3, window: list[int], matched: dict[int, int]
    ) -> dict[int, int]:
        """Project the loop window's points not matched yet into ``kf`` with S_cw (ORB-SLAM
        SearchByProjection(Scw), radius 10 px x the predicted level's scale) and match the free features."""
        taken = np.zeros(len(kf.features), bool)
        taken[list(matched)] = True
        used = set(matched.values())
        rest = [p for p in window if p not in used]
        return project_window(
            self.store, kf, S_cw, rest, self.cfg.loop_search_radius_px, self.cfg.matcher.th_low, taken
        ).matches

    # ---- ORB-SLAM3 sec. VI (LoopClosing::DetectCommonRegionsFromBoW): the common region ----------------

    def _common_regions(self, kf: KeyFrame, out: LoopOutcome) -> AcceptedLoop | None:
        """ORB-SLAM3's DetectCommonRegionsFromBoW over the best ``n_best_candidates`` consistent candidates: each
        gives a hypothesis through :meth:`_common_region` (pooled BoW matches, Sim3 RANSAC, guided matching,
        Sim3 optimisation, refined guided matching); the one with the most refined matches is then verified in
        the current keyframe's covisible keyframes (:meth:`_verify`: accepted, pending or rejected)."""
        best: _Hypothesis | None = None
        for cand_id in out.consistent[: self.cfg.n_best_candidates]:
            info: dict[str, object] = {"candidate": cand_id}
            out.tried.append(info)
            hyp = self._common_region(kf, cand_id, info)
            if hyp is not None and (best is None or len(hyp.matches) > len(best.matches)):
                best = hyp
        if best is None:
            return None
        for info in out.tried:
            if info is not best.info and "rejected" not in info:
                info["rejected"] = "another candidate has more refined matches (ORB-SLAM3: best of the candidates)"
        with self.store.read():
            if not self.store.has_keyframe(best.matched_kf_id) or not self.store.has_keyframe(kf.id):
                best.info["rejected"] = "culled before the verification"
                return None
            return self._verify(kf, best.matched_kf_id, best.S_cw, best.window, best.matches, best.info)

    def _common_region(
        self, kf: KeyFrame, cand_id: int, info: dict[str, object], cand_store: MapStore | None = None
    ) -> _Hypothesis | None:
        """One BoW candidate of ORB-SLAM3's DetectCommonRegionsFromBoW; None with ``info["rejected"]`` saying why.
        cand_store: the map holding the candidate (None: the active map, a loop; another map of the Atlas: a merge,
        whose candidate side nobody changes, so it is read without its lock).

        1. The candidate and its ``candidate_covisibles`` best covisible keyframes: abort when one of them is
           connected to the current keyframe (bAbortByNearKF); else match each by BoW (ratio ``bow_ratio``) and
           pool the matches (a point once), at least ``sim3_min_bow_matches``.
        2. Sim3 RANSAC (Horn) on the pooled matches, in the frame of the keyframe with the most BoW matches (the
           "matched keyframe"; a point another keyframe matched is put in its camera and projected there, as
           ORB-SLAM3's Sim3Solver does), at least ``common_regions_ransac_min_inliers`` inliers.
        3. Guided matching: the points of the matched keyframe and its best covisibles projected with the Sim3
           (``common_regions_search_radius_px``, Hamming <= th_low x ``common_regions_hamming_ratio``), at least
           ``common_regions_min_projected``.
        4. Sim3 optimisation on those matches (at least ``min_inliers_after_sim3_opt`` inliers), then the guided
           matching again with the optimised Sim3 (``common_regions_refined_radius_px``, Hamming <= th_low), at
           least ``common_regions_min_refined``: the hypothesis and its matches."""
        cfg = self.cfg
        store = self.store
        cs = store if cand_store is None else cand_store  # the candidate's side
        assert kf.bow is not None
        with store.read():
            if not cs.has_keyframe(cand_id) or not store.has_keyframe(kf.id):
                info["rejected"] = "culled"
                return None
            group = common_region_keyframes(cs, cand_id, cfg.candidate_covisibles)
            current_side = {kf.id, *store.covisibility.neighbors(kf.id)}
            near = [k for k in group if k in current_side]
            if near:
                info["rejected"] = f"keyframe {near[0]} of the candidate's group is connected to the current keyframe"
                return None
            own_valid = store.has_points(kf.point_ids)
            pooled: dict[int, tuple[int, int, int]] = {}  # current feature -> (point id, keyframe, its feature)
            used: set[int] = set()
            counts: list[int] = []
            for j in group:
                kf_j = cs.get_keyframe(j)
                if kf_j.bow is None:
                    counts.append(0)
                    continue
                pairs = self.place.match(
                    kf.features,
                    kf.bow,
                    kf_j.features,
                    kf_j.bow,
                    cfg.bow_ratio,
                    own_valid,
                    cs.has_points(kf_j.point_ids),
                    max_distance=cfg.matcher.th_low,
                    rotation_bins=cfg.matcher.rotation_bins,
                )
                counts.append(int(pairs.shape[0]))
                left = _camera_1(kf.features, pairs[:, 0]) if pairs.shape[0] else np.zeros(0, bool)
                for f, g in pairs[left]:
                    pid = int(kf_j.point_ids[int(g)])
                    if int(f) in pooled or pid in used:
                        continue
                    pooled[int(f)] = (pid, j, int(g))
                    used.add(pid)
            info["bow_matches"] = len(pooled)
            if len(pooled) < cfg.sim3_min_bow_matches:
                info["rejected"] = f"{len(pooled)} pooled BoW matches < {cfg.sim3_min_bow_matches}"
                return None
            matched_id = group[int(np.argmax(counts))]
            matched = cs.get_keyframe(matched_id)
            i1 = np.array(sorted(pooled), dtype=np.int64)
            xyz1 = self._points_c(kf, i1)
            T_m_w = matched.T_c_w.copy()
            xyz2 = np.stack([cs.get_point(pooled[int(f)][0]).xyz_w for f in i1]) @ T_m_w[:3, :3].T + T_m_w[:3, 3]
            level2 = np.array(
                [cs.get_keyframe(pooled[int(f)][1]).features.level[pooled[int(f)][2]] for f in i1], dtype=np.int64
            )
        info["matched_kf"] = matched_id
        front = xyz2[:, 2] > 1e-9
        i1, xyz1, xyz2, level2 = i1[front], xyz1[front], xyz2[front], level2[front]
        K1, K2 = kf.camera.K, matched.camera.K
        uv1 = kf.features.uv_undist_px[i1].astype(np.float64)
        uv2 = _project_camera(matched.camera, xyz2)
        sigma2_2 = np.power(matched.features.scale_factor, 2.0 * level2.astype(np.float64))
        ransac = ransac_sim3(
            xyz1,
            xyz2,
            uv1,
            uv2,
            K1,
            K2,
            kf.features.level_sigma2()[i1],
            sigma2_2,
            self.rng,
            fix_scale=kf.features.bf > 0.0,
            probability=cfg.sim3_ransac_probability,
            min_inliers=cfg.common_regions_ransac_min_inliers,
            max_iterations=cfg.sim3_ransac_max_iterations,
            chi2=cfg.chi2.sim3_ransac,
            project1=_image_projection(kf.camera),
            project2=_image_projection(matched.camera),
        )
        info["ransac_inliers"] = int(ransac.inliers.sum())
        if ransac.S_12 is None:
            info["rejected"] = "Sim3 RANSAC found no hypothesis"
            return None
        loose = int(cfg.matcher.th_low * cfg.common_regions_hamming_ratio)
        with store.read():
            if not cs.has_keyframe(matched_id) or not store.has_keyframe(kf.id):
                info["rejected"] = "culled during the Sim3 RANSAC"
                return None
            window = points_of(cs, common_region_keyframes(cs, matched_id, cfg.candidate_covisibles))
            S_cw = ransac.S_12 @ sim3_of_pose(T_m_w)
            guided = project_window(cs, kf, S_cw, window, cfg.common_regions_search_radius_px, loose)
            info["projected_matches"] = len(guided.matches)
            if len(guided.matches) < cfg.common_regions_min_projected:
                info["rejected"] = f"{len(guided.matches)} projected matches < {cfg.common_regions_min_projected}"
                return None
            problem = self._sim3_problem(kf, matched, matched_id, ransac.S_12, guided.matches, cs)
        if problem is None:
            info["rejected"] = "no projected match has a point in the current keyframe"
            return None
        opt = self.optimizer.optimize_sim3(problem)
        info["optimized_inliers"] = int(opt.inliers.sum())
        if opt.inliers.sum() < cfg.min_inliers_after_sim3_opt:
            info["rejected"] = f"{int(opt.inliers.sum())} inliers after Sim3 optimization"
            return None
        S_cm = Sim3.from_matrix(opt.S_12)
        with store.read():
            if not cs.has_keyframe(matched_id) or not store.has_keyframe(kf.id):
                info["rejected"] = "culled during the Sim3 optimization"
                return None
            S_cw = S_cm @ sim3_of_pose(T_m_w)
            refined = project_window(
                cs, kf, S_cw, window, cfg.common_regions_refined_radius_px, cfg.matcher.th_low
            ).matches
            info["loop_matches"] = len(refined)
            info["scale"] = S_cm.s
            if len(refined) < cfg.common_regions_min_refined:
                info["rejected"] = f"{len(refined)} refined matches < {cfg.common_regions_min_refined}"
                return None
            verify_window = verification_window(cs, matched_id, cfg.candidate_covisibles, kf.id)
        return _Hypothesis(matched_id, S_cw, refined, verify_window, info)

    def _sim3_problem(
        self,
        kf: KeyFrame,
        matched: KeyFrame,
        matched_id: int,
        S_cm: Sim3,
        matches: dict[int, int],
        matched_store: MapStore | None = None,
    ) -> Sim3Problem | None:
        """ORB-SLAM3 OptimizeSim3(..., bAllPoints = true) on guided matches (current feature -> window point): a
        match counts when the current feature has a live point; its observation in the matched keyframe is the
        keypoint there if the matched keyframe sees the point, else the point's projection (at the current
        feature's level). matched_store: the map of ``matched`` (None: the active map). Called under the read lock."""
        store = self.store
        ms = store if matched_store is None else matched_store
        rows = [
            (f, int(kf.point_ids[f]), pid)
            for f, pid in sorted(matches.items())
            if kf.point_ids[f] >= 0 and store.has_point(int(kf.point_ids[f]))
        ]
        if not rows:
            return None
        feats = np.array([r[0] for r in rows], dtype=np.int64)
        T_c_w, T_m_w = kf.T_c_w, matched.T_c_w
        xyz1 = np.stack([store.get_point(r[1]).xyz_w for r in rows]) @ T_c_w[:3, :3].T + T_c_w[:3, 3]
        xyz2 = np.stack([ms.get_point(r[2]).xyz_w for r in rows]) @ T_m_w[:3, :3].T + T_m_w[:3, 3]
        uv2 = _project_camera(matched.camera, xyz2)
        level1 = kf.features.level[feats].astype(np.int64)
        level2 = level1.copy()
        for n, (_, _, pid) in enumerate(rows):
            g = ms.get_point(pid).observations.get(matched_id)
            # a camera-2 keypoint is no observation here (ORB-SLAM3: get<0> of GetIndexInKeyFrame is -1)
            if g is not None and _camera_1(matched.features, np.array([g], np.int64))[0]:
                uv2[n] = matched.features.uv_undist_px[g]
                level2[n] = int(matched.features.level[g])
        seen = np.isfinite(uv2).all(axis=1)  # a fisheye model's projection can be undefined (beyond its field of view)
        if not seen.all():
            feats, level1, level2 = feats[seen], level1[seen], level2[seen]
            xyz1, xyz2, uv2 = xyz1[seen], xyz2[seen], uv2[seen]
            if feats.shape[0] < 3:
                return None
        return Sim3Problem(
            S_12_init=S_cm.matrix(),
            xyz1_c1=xyz1,
            xyz2_c2=xyz2,
            uv1_px=kf.features.uv_undist_px[feats].astype(np.float64),
            uv2_px=uv2,
            level1=level1,
            level2=level2,
            intrinsics1=intrinsics_of(kf.camera.K),
            intrinsics2=intrinsics_of(matched.camera.K),
            scale_factor=kf.features.scale_factor,
            chi2=self.cfg.chi2.sim3,
            fix_scale=kf.features.bf > 0.0,  # stereo/RGB-D: scale observable (ORB-SLAM2 mbFixScale)
            **_sim3_cameras(kf.camera, matched.camera),
        )

    # ---- ORB-SLAM3 sec. VI: geometric verification -----------------------------------------------------

    def _verify(
        self,
        kf: KeyFrame,
        cand_id: int,
        S_cw: Sim3,
        window: list[int],
        matches: dict[int, int],
        info: dict[str, object],
    ) -> AcceptedLoop | None:
        """Check the correction the hypothesis implies (ORB-SLAM3's rotation bound), then the hypothesis in the
        current keyframe and its covisible keyframes. Enough agreeing covisible keyframes accept the loop now;
        some keep it pending for the next keyframes; none reject it."""
        cfg = self.cfg
        turn = loop_rotation_deg(kf.T_c_w, S_cw)
        info["correction_rotation_deg"] = round(turn, 2)
        if turn > cfg.max_loop_rotation_deg:
            info["rejected"] = (
                f"verification: the loop would turn the map by {turn:.1f} deg > {cfg.max_loop_rotation_deg} deg"
            )
            return None
        own, _ = check_keyframe(self.store, kf, S_cw, window, self._thresholds)
        checks: list[KeyframeCheck] = [own]
        if own.agrees:
            checks += check_covisibles(
                self.store, kf, S_cw, window, self._thresholds, cfg.verify_covisible_keyframes, cfg.verify_coincidences
            )
        agreeing = sum(c.agrees for c in checks[1:])
        info["verification"] = [c.as_dict() for c in checks]
        info["agreeing"] = agreeing
        if not own.agrees:
            info["rejected"] = f"verification: the current keyframe disagrees ({own.why})"
            return None
        if agreeing >= cfg.verify_coincidences:
            return self._accept(cand_id, S_cw, matches)
        if agreeing == 0:
            info["rejected"] = "verification: no covisible keyframe agrees"
            return None
        self._pending = PendingLoop(cand_id, kf.id, kf.T_c_w.copy(), S_cw, window, agreeing, 0, matches)
        info["rejected"] = (
            f"verification: {agreeing} of {cfg.verify_coincidences} keyframes agree; pending for the next keyframes"
        )
        return None

    def _check_pending(self, kf: KeyFrame, out: LoopOutcome) -> AcceptedLoop | None:
        """ORB-SLAM3's confirmation of a pending loop by a new keyframe: carry the hypothesis to it with the
        tracked motion, check it there; accept after ``verify_coincidences`` agreeing keyframes, drop it after
        ``verify_max_misses`` consecutive disagreeing ones."""
        pending = self._pending
        assert pending is not None
        if not self.store.has_keyframe(pending.loop_kf_id):
            self._pending = None
            out.pending = {"loop_kf": pending.loop_kf_id, "state": "dropped", "why": "loop keyframe culled"}
            return None
        cfg = self.cfg
        step = advance_pending(
            self.store,
            pending,
            kf,
            self._thresholds,
            cfg.verify_coincidences,
            cfg.verify_max_misses,
            self._refine_pending if cfg.geometric_verification else None,
        )
        out.pending = {"loop_kf": pending.loop_kf_id, **pending_record(pending, step)}
        if step.state == "dropped":
            self._pending = None
        if step.state == "accepted":
            return self._accept(pending.loop_kf_id, step.S_k_w, step.matches)
        return None

    def _refine_pending(self, kf: KeyFrame, S_k_w: Sim3, proj: WindowProjection) -> str:
        """ORB-SLAM3 DetectAndReffineSim3FromLastKF after the projection found enough matches: the Sim3 between
        ``kf`` and the pending loop's keyframe optimised on those matches must keep more than
        ``confirm_min_optimized`` inliers, and the projection at least ``confirm_min_matches`` matches (ORB-SLAM3
        re-projects with the same estimate, so this is the projection's count). Why it fails, "" if it agrees.
        Called under the read lock."""
        pending = self._pending
        assert pending is not None
        return self._refine_hypothesis(kf, self.store, pending.loop_kf_id, S_k_w, proj)

    def _refine_hypothesis(
        self, kf: KeyFrame, matched_store: MapStore, matched_id: int, S_k_w: Sim3, proj: WindowProjection
    ) -> str:
        """DetectAndReffineSim3FromLastKF's checks of a hypothesis S_k_w between ``kf`` and the keyframe
        ``matched_id`` of ``matched_store`` (the active map for a loop, another map for a merge) on the projection's
        matches ``proj``: why it fails, "" if it agrees. Called under the read lock."""
        cfg = self.cfg
        if len(proj.matches) < cfg.confirm_min_matches:
            return f"{len(proj.matches)} matches < {cfg.confirm_min_matches}"
        matched = matched_store.get_keyframe(matched_id)
        S_km = S_k_w @ sim3_of_pose(matched.T_c_w).inverse()
        problem = self._sim3_problem(kf, matched, matched_id, S_km, proj.matches, matched_store)
        inliers = 0 if problem is None else int(self.optimizer.optimize_sim3(problem).inliers.sum())
        if inliers <= cfg.confirm_min_optimized:
            return f"{inliers} inliers after Sim3 optimization <= {cfg.confirm_min_optimized}"
        return ""

    # ---- VII-C/D: correction ----------------------------------------------------------------------------

    def _correct(
        self, kf: KeyFrame, loop_kf_id: int, S_cw: Sim3, loop_matches: dict[int, int], out: LoopOutcome
    ) -> None:
        """ORB-SLAM CorrectLoop, local mapping parked by the caller. The map's write lock is held only to write: what
        only reads the map (the Sim3 propagation and the corrected points' positions and normals, the essential-graph
        problem, the optimized map's poses, positions and normals) runs under the read lock, so tracking goes on
        meanwhile (``read_then_write``); ORB-SLAM holds mMutexMapUpdate over all of it. Nothing but this step writes
        the map in between (local mapping is parked, the global BA aborted, tracking only counts visible/found
        points): the map each write finds is the one computed on, as if it all ran under one write lock."""
        store = self.store
        with store.write():
            store.update_connections(kf.id)

        def propagate() -> tuple[LoopCorrection, dict[int, set[int]], MapMove]:
            corr = propagate_loop_sim3(store, kf.id, S_cw)
            before = {k: set(store.covisibility.neighbors(k)) for k in corr.corrected}
            return corr, before, loop_correction_move(store, corr)[0]

        def correct_and_fuse(
            prepared: tuple[LoopCorrection, dict[int, set[int]], MapMove],
        ) -> tuple[LoopCorrection, dict[int, set[int]]]:
            corr, before, move = prepared
            write_map_move(store, move)
            return corr, self._fuse_loop(kf, loop_kf_id, loop_matches, corr, before)

        corr, loop_connections = read_then_write(store, propagate, correct_and_fuse)
        t_eg = time.perf_counter()
        with store.read():
            problem, eg_kf_ids = essential_graph_problem(
                store, loop_kf_id, kf.id, corr, loop_connections, self.cfg.theta_min
            )
        # The optimization itself runs without the map lock, as ORB-SLAM's OptimizeEssentialGraph does (it locks
        # the map only to write its result): tracking goes on meanwhile on the half-corrected map. Nothing else
        # changes keyframe poses or points in between: local mapping is parked for the whole loop-closing step.
        result = self.optimizer.optimize_essential_graph(problem)

        def commit(move: MapMove) -> None:
            write_map_move(store, move)
            store.add_loop_edge(kf.id, loop_kf_id)
            store.bump_epoch()

        read_then_write(store, lambda: essential_graph_move(store, problem, result, eg_kf_ids), commit)
        out.timings_ms["essential_graph_ms"] = (time.perf_counter() - t_eg) * 1e3
        out.essential_graph_edges = int(problem.edge_i.shape[0])
        if self.cfg.global_ba:
            t_ba = time.perf_counter()
            self.start_global_ba(kf.id)
            out.timings_ms["global_ba_start_ms"] = (time.perf_counter() - t_ba) * 1e3

    def _fuse_loop(
        self,
        kf: KeyFrame,
        loop_kf_id: int,
        loop_matches: dict[int, int],
        corr: LoopCorrection,
        before: dict[int, set[int]],
    ) -> dict[int, set[int]]:
        """Loop fusion after the neighbourhood's correction (ORB-SLAM CorrectLoop, the write lock held): the loop's
        points replace the current keyframe's duplicates and are fused into the corrected keyframes, whose
        connections are then updated. ``before``: each corrected keyframe's neighbours before. Returns the new loop
        connections (keyframe id -> newly linked keyframes outside the corrected ones; the current keyframe is
        linked to the loop keyframe)."""
        store = self.store
        for feat, pid in sorted(loop_matches.items()):
            if not store.has_point(pid):
                continue
            existing = int(kf.point_ids[feat])
            if existing >= 0 and store.has_point(existing):
                if existing != pid:
                    replace_point(store, store.get_point(existing), store.get_point(pid))
            elif kf.id not in store.get_point(pid).observations:
                store.add_observation(pid, kf.id, feat)
        # the distinct points of the loop keyframe and its neighbours, sorted (one mark per id, no Python step per id)
        loop_points = unique_point_ids(
            [store.get_keyframe(k).point_ids for k in [loop_kf_id, *store.covisibility.neighbors(loop_kf_id)]]
        ).tolist()
        for k in sorted(corr.corrected):
            if store.has_keyframe(k):
                fuse_points(
                    store,
                    store.get_keyframe(k),
                    loop_points,
                    self.cfg.loop_fuse_radius_px,
                    incoming_wins=True,
                    max_distance=self.cfg.matcher.th_low,
                    chi2_gate=self.cfg.chi2.fuse_mono,
                )
        loop_connections: dict[int, set[int]] = {}
        for k in sorted(corr.corrected):
            if not store.has_keyframe(k):
                continue
            store.update_connections(k)
            linked = set(store.covisibility.neighbors(k)) - before.get(k, set()) - set(corr.corrected)
            if linked:
                loop_connections[k] = linked
        loop_connections.setdefault(kf.id, set()).add(loop_kf_id)
        return loop_connections

    # ---- global BA after a loop (ORB-SLAM2 RunGlobalBundleAdjustment) ----------------------------------------

    def start_global_ba(self, loop_kf_id: int) -> None:
        """Global BA of the whole map after the loop at ``loop_kf_id`` (slamkit/pipeline/global_ba.py): in line
        when no ``park_mapping`` is set (the sequential runner: deterministic), else in its own thread, which
        parks local mapping only to write its result (ORB-SLAM2: a thread; local mapping stopped for the update).
        A running global BA is aborted first (ORB-SLAM2 CorrectLoop: mbStopGBA)."""
        self.abort_global_ba()
        store = self.store
        chi2 = self.cfg.chi2
        with store.read():
            snap = snapshot_global_ba(store, self.cfg.global_ba_iterations, chi2.mono, chi2.stereo)
        if snap is None:
            return
        token = threading.Event()
        self._gba_abort = token
        if self.park_mapping is None:
            self._run_global_ba(store, snap, token, loop_kf_id)
            return
        self._gba_thread = threading.Thread(
            target=self._run_global_ba, args=(store, snap, token, loop_kf_id), name="global-ba", daemon=True
        )
        self._gba_thread.start()

    def _run_global_ba(self, store: MapStore, snap: BundleSnapshot, token: threading.Event, loop_kf_id: int) -> None:
        out = GlobalBAOutcome(loop_kf_id, int(snap.kf_ids.size), int(snap.point_ids.size))
        t0 = time.perf_counter()
        try:
            result = optimize_global_ba(self.optimizer, snap, token)
            out.ms = (time.perf_counter() - t0) * 1e3
            out.aborted = result.aborted or token.is_set()
            if not out.aborted:
                with self.park_mapping() if self.park_mapping is not None else contextlib.nullcontext():
                    if token.is_set():
                        out.aborted = True
                    else:
                        with store.write():
                            out.propagated_keyframes, out.propagated_points = commit_global_ba(store, snap, result)
        except Exception as exc:  # a failed global BA leaves the map as the loop correction left it
            self.global_ba_error = exc
            log.exception("global BA after the loop at keyframe %d failed", loop_kf_id)
            raise
        finally:
            self.global_bas.append(out)
        log.info(
            "global BA after the loop at keyframe %d: %d keyframes, %d points, %.0f ms%s; propagated to %d keyframes"
            " and %d points added meanwhile",
            loop_kf_id,
            out.keyframes,
            out.points,
            out.ms,
            " (aborted)" if out.aborted else "",
            out.propagated_keyframes,
            out.propagated_points,
        )

    def abort_global_ba(self) -> bool:
        """Stop a running global BA (a new loop, a map reset; ORB-SLAM2 mbStopGBA) and wait for its thread; an
        aborted global BA writes nothing. Returns whether one was running (ORB-SLAM3 isRunningGBA(): a merge
        relaunches it on the merged map)."""
        thread = self._gba_thread
        running = thread is not None and thread.is_alive()
        if self._gba_abort is not None:
            self._gba_abort.set()
        self.join_global_ba()
        return running

    def join_global_ba(self) -> None:
        """Wait for a running global BA to finish (the end of a run: ORB-SLAM2 Shutdown waits for it)."""
        thread = self._gba_thread
        if thread is not None:
            thread.join()
            self._gba_thread = None
