"""The Tracker (ORB-SLAM sec. V): the tracking thread's state machine and the order of its steps.

``Tracker.step(data, camera, mapping)`` handles one frame: ORB extraction by the front end, initialisation
(sec. IV) until a map exists, then the initial pose from the constant-velocity motion model or the reference
keyframe (V-B, :mod:`.motion_model`, :mod:`.reference_keyframe`) or, when lost, relocalization (V-C,
:mod:`.relocalization`), tracking of the local map (V-D, :mod:`.local_map`) and the new-keyframe decision (V-E,
:mod:`.keyframe_decision`). It returns a :class:`~slamkit.pipeline.outcomes.TrackingOutcome`.

One owner per decision. Tracking decides; the runner, which owns the threads, carries out what needs them:

- local mapping's state comes in as data (:class:`~slamkit.pipeline.outcomes.MappingState`), filled by the runner
  each frame; nothing is installed into the tracker;
- a keyframe tracking makes is *not* put in the map here: it travels in ``outcome.new_keyframes`` to local mapping,
  whose insertion (slamkit/pipeline/keyframe_insertion.py) is the only one;
- "a keyframe is wanted but local mapping is busy" is the outcome's ``keyframe = MAPPING_BUSY``: the runner stops
  the running local BA (real time) or waits for local mapping and then calls :meth:`Tracker.make_keyframe`;
- what to do when lost is decided here (slamkit/pipeline/lost.py, ORB-SLAM3): a map of at most
  ``reset_lost_map_max_keyframes`` keyframes is reset, a bigger one is kept in the Atlas and, after
  ``time_recently_lost_s`` of failed relocalization, a new map starts. The outcome's ``lost_decision`` says
  RESET_MAP or NEW_MAP: the runner parks local mapping and loop closing and calls :meth:`Tracker.reset` or
  :meth:`Tracker.start_new_map`, so the tracker never calls into the runner and no thread works on a map while the
  active map changes.

Localization mode (``localization_only``, ``mode=localization``; ORB-SLAM2/3 Tracking::Track's mbOnlyTracking branch)
tracks and relocalizes against the loaded map and never changes it: no keyframe (NeedNewKeyFrame returns false), so no
new point, and when lost it relocalizes for as long as it takes (no reset, no new map). While the last frame tracked
enough map points (mbVO false) the initial pose comes from the motion model alone (more than
``localization_min_motion_model_inliers - 1`` inliers) or, without a velocity, the reference keyframe, then the local
map is tracked. When it tracked mostly visual-odometry points (mbVO: fewer than ``min_inliers_after_pose_opt`` of its
matches on map points) the frame is tracked twice, by the motion model and by relocalization: a successful
relocalization wins and brings the local map back, else the motion model's pose is kept without the local map.
Visual-odometry points are ORB-SLAM2's temporary points of a stereo/RGB-D last frame (UpdateLastFrame, only in this
mode); slamkit does not make them yet, so every match is a map point and mbVO only follows a failed motion model.
One deliberate difference: a relocalization from LOST clears mbVO (ORB-SLAM2 leaves it as it was, so the frame after a
lost spell skipped TrackLocalMap).

A new session on a loaded Atlas (``map.load=FILE``; ``session_start``, docs/atlas.md "Multi-session"). ORB-SLAM3's
System::LoadAtlas is followed by Atlas::CreateNewMap: the new session initialises a new map, which joins the loaded
ones only by map merging (its relocalization searches the active map only, so it never relocalizes in a loaded map).
``session_start``:

- ``"new_map"``: exactly that;
- ``"reloc_or_new_map"`` (the app's default): the same, except that while the new map is being initialised each frame
  first tries to relocalize in the loaded active map (V-C, then the local map as on any lost frame); the first success
  ends the attempt and the session goes on in the loaded map (no map is made). The first initialisation that makes a
  map ends it too: the new map becomes the active one (``Atlas.create_map``; the loaded one stays in the Atlas);
- ``"relocalize"``: the loaded active map is the session's map: tracking starts lost on it and relocalizes (a new map
  only after ``time_recently_lost_s`` of failure, the lost policy; the behaviour before multi-session).

Deterministic given the rng (the initializer's RANSAC).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from slamkit.geometry.sim3 import Sim3
from slamkit.interfaces import BowDescription, Camera, FrontEnd, Initializer, MapStore, Optimizer, PlaceRecognizer
from slamkit.map.atlas import Atlas
from slamkit.map.entities import KeyFrame
from slamkit.map.mapfile_run import SESSION_STARTS
from slamkit.pipeline.config import TrackingConfig
from slamkit.pipeline.frame import Frame, ImageBounds, with_stereo_partners
from slamkit.pipeline.initialization import (
    MonocularInitialization,
    create_initial_map,
    create_stereo_initial_map,
    new_keyframe,
)
from slamkit.pipeline.lost import LostDecision, LostPolicy, LostRecord, decide_when_lost
from slamkit.pipeline.map_merging import moved_pose
from slamkit.pipeline.map_points import orbslam_observation_counts
from slamkit.pipeline.outcomes import KeyFrameDecision, MappingState, TrackingOutcome, TrackingState
from slamkit.pipeline.pose_optimization import optimize_pose as motion_only_ba
from slamkit.pipeline.startup import freeze_startup_heap, load_cached_kernels
from slamkit.pipeline.tracking.frame_pose import PoseRefiner
from slamkit.pipeline.tracking.keyframe_decision import (
    KeyFrameFacts,
    decide_keyframe,
    max_frames_of,
    reference_min_observations,
)
from slamkit.pipeline.tracking.local_map import track_local_map
from slamkit.pipeline.tracking.motion_model import (
    pose_relative_to_reference,
    track_with_motion_model,
    update_last_frame,
    velocity,
)
from slamkit.pipeline.tracking.reference_keyframe import track_reference_keyframe
from slamkit.pipeline.tracking.relocalization import relocalize
from slamkit.problems import PoseOnlyProblem, PoseOnlyResult
from slamkit.sensors import FrameData

log = logging.getLogger("slamkit.tracking")

F64 = NDArray[np.float64]

#: Local mapping's state for a tracker with no local mapping thread beside it (a test stepping a tracker alone).
IDLE_MAPPING = MappingState(idle=True, accepting_keyframes=True)


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
        fps: float = 30.0,
        localization_only: bool = False,
        session_start: str = "relocalize",
    ) -> None:
        """frontend: turns each packet into the frame's observation record (it holds the feature extractors).
        pose_optimizer: motion-only BA of tracking; default the compiled one of
        slamkit.pipeline.pose_optimization (same algorithm as ``Optimizer.optimize_pose``, a few hundred times
        cheaper and GIL-free); pass ``optimizer.optimize_pose`` to run it through the optimizer backend.
        fps: the camera's frame rate (Hz), ORB-SLAM's mMaxFrames unless ``keyframe_max_frames`` sets it.
        localization_only: ORB-SLAM's localization mode (``mode=localization``, see the module docstring): the Atlas's
        active map must have keyframes; tracking never makes a keyframe and never resets or replaces the map.
        session_start: what a session does on an Atlas whose active map has keyframes (a loaded map): "new_map",
        "reloc_or_new_map" or "relocalize" (module docstring; ignored in localization mode, which relocalizes)."""
        if session_start not in SESSION_STARTS:
            raise ValueError(f"session_start={session_start!r}: expected one of {', '.join(SESSION_STARTS)}")
        self.cfg = cfg
        self.max_frames = max_frames_of(cfg, fps)  # ORB-SLAM mMaxFrames (frames)
        self.frontend = frontend
        self.optimizer = optimizer
        self.optimize_pose = pose_optimizer or motion_only_ba
        self.atlas = atlas  # the maps; tracking works on the active one (``store``)
        self.localization_only = localization_only  # ORB-SLAM mbOnlyTracking
        self._vo = False  # ORB-SLAM2 mbVO (localization mode): the last frame tracked few map points
        self.lost_policy = LostPolicy(
            cfg.reset_lost_map_max_keyframes, cfg.time_recently_lost_s, map_read_only=localization_only
        )
        self._lost_since_s: float | None = None  # timestamp of the first frame of the current lost spell
        self.place = place  # bag of words: reference-keyframe matching and relocalization (ORB-SLAM V-B, V-C)
        self.refiner = PoseRefiner(cfg, self.store, self.optimize_pose)
        self.relocalizations = 0
        # an Atlas whose active map already has keyframes (a saved map, map.load=FILE): relocalize in it first, or
        # initialise a new map for the session (``session_start``, module docstring)
        loaded = self.store.n_keyframes() > 0
        if localization_only and not loaded:
            raise ValueError("localization only: the active map has no keyframe to localize against")
        self.session_start = "relocalize" if localization_only or not loaded else session_start
        #: the loaded map the session may still relocalize in while its own new map is not initialised
        self._loaded_map_id: int | None = None
        if self.session_start == "relocalize":
            self.state = TrackingState.LOST if loaded else TrackingState.NOT_INITIALIZED
        else:
            self.state = TrackingState.NOT_INITIALIZED
            if self.session_start == "reloc_or_new_map":
                self._loaded_map_id = self.atlas.active_id
        #: the session's new map is still to be made (Atlas.create_map) when its initialisation succeeds
        self._new_map_pending = self.session_start != "relocalize"
        self.init = MonocularInitialization(cfg, initializer, rng)
        self.rng = rng  # the initializer's RANSAC and the relocalization's PnP RANSAC
        self.last_frame: Frame | None = None
        # the frame of the last step (its keypoints and the map points they were matched to), for listeners such as
        # a viewer: read it after ``step`` returns, in the tracking thread
        self.current_frame: Frame | None = None
        self.velocity: F64 | None = None  # T_cur_last of the last two tracked frames
        self.reference_kf_id: int | None = None
        self.last_kf_frame_index = -(10**9)
        self.last_reloc_frame_index = -(10**9)
        self._init_frame_index: int | None = None  # the frame that initialised the active map
        self._bounds: dict[int, ImageBounds] = {}
        self._last_T_l_r: F64 | None = None
        self._frame_bow: BowDescription | None = None
        # the scale of the map moves (merges) since the motion model's velocity was last brought up to date
        self._moved_scale = 1.0
        # every move of the active map (x_new = G x_old) in order; a TrackingOutcome's map_moves counts the ones its
        # poses are expressed after (follow_map_moves brings an outcome past later ones)
        self._moves: list[Sim3] = []
        self._moved_lock = threading.Lock()

    @property
    def store(self) -> MapStore:
        """The active map of the Atlas."""
        return self.atlas.active

    # ---- public ------------------------------------------------------------------------------

    def warm_up(self, camera: Camera) -> None:
        """One-off work before a timed run (the runner calls it before the clock starts); changes no state of the
        tracker and no result. Runs the front end's feature extractors once on a synthetic image and throws the
        result away (the first extraction loads compiled kernels and starts thread pools), loads every other cached
        compiled kernel (:func:`slamkit.pipeline.startup.load_cached_kernels`: the BA, matching, bag-of-words and pose
        kernels the frames after initialisation call first, 0.5-0.9 s of loading that dropped those frames in real
        time) and freezes the start-up heap out of the garbage collector's full collections
        (:func:`slamkit.pipeline.startup.freeze_startup_heap`: 70-200 ms pauses with the GIL held, every few seconds)."""
        self.frontend.warm_up(camera)
        done = load_cached_kernels()
        frozen = freeze_startup_heap()
        log.info(
            "warm-up: %d cached signatures of %d compiled kernels loaded in %.2f s; %d start-up objects frozen out "
            "of the garbage collector",
            done.loaded,
            done.kernels,
            done.seconds,
            frozen,
        )

    def step(
        self,
        data: FrameData,
        camera: Camera,
        mapping: MappingState | Callable[[], MappingState] = IDLE_MAPPING,
    ) -> TrackingOutcome:
        """Track one frame. camera: the dataset's (left) camera. mapping: local mapping's state (the runner's;
        default: idle, for a tracker stepped without a local mapping thread), or a function giving it, called once the
        frame's features are extracted and before it is tracked (the threaded runner may wait there for local
        mapping: docs/runtime.md)."""
        t0 = time.perf_counter()
        given: list[MappingState] = []

        def mapping_now() -> MappingState:
            if not given:
                given.append(mapping() if callable(mapping) else mapping)
            return given[0]

        initializing = self.state == TrackingState.NOT_INITIALIZED
        timings: dict[str, float] = {}
        if initializing and self._loaded_map_id is not None:
            # a new session on a loaded map: relocalization there first, with the tracking extractor
            frame = self._frame(data, camera, False, timings)
            outcome = self._relocalize_in_loaded_map(frame, timings, mapping_now())
            outcome.map_moves = self._n_moves()  # no merge runs before the session's first tracked frame
            if outcome.state == TrackingState.OK:
                timings["track_ms"] = (time.perf_counter() - t0) * 1e3
                outcome.timings_ms.update(timings)
                return outcome
            self.state = TrackingState.NOT_INITIALIZED  # the frame goes to the new map's initialisation
            self._lost_since_s = None
            self.velocity = None
        # ORB-SLAM extracts twice the features on frames used for monocular initialisation (the front end's job),
        # and ORB-SLAM3 goes on with that extractor for a while after initialising (_init_extractor_window)
        frame = self._frame(data, camera, initializing or self._in_init_extractor_window(data.index), timings)
        if initializing:
            outcome = self._initialize(frame)
            outcome.map_moves = self._n_moves()  # a map being initialised is not merged
        else:
            outcome = self._track(frame, timings, mapping_now())
        timings["track_ms"] = (time.perf_counter() - t0) * 1e3
        outcome.timings_ms.update(timings)
        return outcome

    def _frame(self, data: FrameData, camera: Camera, initializing: bool, timings: dict[str, float]) -> Frame:
        """The frame of ``data`` (features by the initialisation extractor when ``initializing``); the extraction's
        time is added to ``timings["extract_ms"]``."""
        t0 = time.perf_counter()
        features = self.frontend.observe(data, camera, initializing)
        timings["extract_ms"] = timings.get("extract_ms", 0.0) + (time.perf_counter() - t0) * 1e3
        bounds2 = self._bounds_of(features.camera_2) if features.two_cameras else None
        frame = Frame.create(data.index, data.timestamp_s, camera, features, self._bounds_of(camera), bounds2)
        self.current_frame = frame
        return frame

    def uses_tracking_extractor(self, data: FrameData) -> bool:
        """Whether the frame of ``data``, were it tracked now, would get the tracking extractor (not a monocular
        initialisation's, nor the frames after it that ORB-SLAM3 gives that extractor too). A hint for extraction
        ahead of tracking (slamkit/runtime/extract_ahead.py), read from another thread: the state may change before
        the frame is tracked, which costs that extraction only."""
        return self.state != TrackingState.NOT_INITIALIZED and not self._in_init_extractor_window(data.index)

    def _in_init_extractor_window(self, frame_index: int) -> bool:
        """Whether a frame of a tracked map still gets the initialisation extractor: with
        ``init_extractor_after_init``, the mMaxFrames frames after the initialising one (ORB-SLAM3
        Tracking::GrabImageMonocular extracts with mpIniORBextractor while ``lastID - initID < mMaxFrames``;
        it compares the previous frame's id with the initial keyframe's id, a keyframe counter, where slamkit
        counts frames from the initialising frame). Without it, never (ORB-SLAM2)."""
        if not self.cfg.init_extractor_after_init or self._init_frame_index is None:
            return False
        return frame_index - self._init_frame_index <= self.max_frames

    def make_keyframe(self, outcome: TrackingOutcome) -> TrackingOutcome:
        """Make the keyframe the last step wanted when local mapping was busy (``outcome.keyframe ==
        MAPPING_BUSY``), once the runner has waited for local mapping; returns the outcome with it."""
        frame = self.last_frame
        if outcome.keyframe != KeyFrameDecision.MAPPING_BUSY or frame is None or frame.index != outcome.frame_index:
            raise ValueError(f"frame {outcome.frame_index}: no keyframe is pending for the last tracked frame")
        kf = self._new_keyframe(frame)
        return dataclasses.replace(
            outcome,
            new_keyframes=[kf],
            keyframe=KeyFrameDecision.INSERT,
            reference_kf_id=kf.id,
            T_ref_w=kf.T_c_w,
            timings_ms=dict(outcome.timings_ms),
        )

    def map_moved(self, G_new_old: Sim3) -> None:
        """A map merge moved the active map by the similarity x_new = G x_old (``MapMerge.G``; called by the runner,
        from the loop-closing thread under the map's write lock in the threaded runner). The motion model's velocity
        T_cur_last and the last frame's pose relative to its reference keyframe were measured in the old scale: their
        translations are multiplied by G's scale at the next frame, under the map's read lock (a frame is tracked
        wholly before the move or wholly after it: ``_track`` holds the read lock throughout). ORB-SLAM3's visual
        MergeLocal leaves the tracker's velocity as it is (its MergeLocal2 calls Tracking::UpdateFrameIMU with scale
        1): a monocular merge of scale far from 1 then loses a frame or two (docs/BENCHMARKS.md, "Map merging")."""
        with self._moved_lock:
            self._moved_scale *= float(G_new_old.s)
            self._moves.append(G_new_old)

    def _n_moves(self) -> int:
        with self._moved_lock:
            return len(self._moves)

    def follow_map_moves(self, outcome: TrackingOutcome) -> None:
        """Bring a step's outcome past the map moves made since the frame was tracked (``outcome.map_moves``): its pose,
        its reference keyframe's pose as tracking read it, the keyframes it made (not in the map yet: the move did not
        see them) and the last frame's pose, each moved as the map was. The threaded runner calls it under the active
        map's read lock before it records the frame and hands its keyframes to local mapping, so no move comes between
        (ORB-SLAM holds mMutexMapUpdate for the whole of Tracking::Track, keyframe creation included)."""
        with self._moved_lock:
            moves = self._moves[outcome.map_moves :]
            outcome.map_moves = len(self._moves)
        if not moves:
            return
        G = moves[0]
        for later in moves[1:]:
            G = later @ G
        if outcome.T_c_w is not None:
            outcome.T_c_w = moved_pose(outcome.T_c_w, G)
        if outcome.T_ref_w is not None:
            outcome.T_ref_w = moved_pose(outcome.T_ref_w, G)
        outcome.new_keyframes = [dataclasses.replace(kf, T_c_w=moved_pose(kf.T_c_w, G)) for kf in outcome.new_keyframes]
        last = self.last_frame
        if last is not None and last.index == outcome.frame_index and last.T_c_w is not None:
            last.T_c_w = moved_pose(last.T_c_w, G)

    def _apply_map_moves(self) -> None:
        """Bring the velocity and the last frame's relative pose to the scale of the map moves since the last frame
        (``map_moved``); the caller holds the map's read lock."""
        with self._moved_lock:
            scale, self._moved_scale = self._moved_scale, 1.0
        if scale == 1.0:
            return
        last = self.last_frame
        if self._last_T_l_r is None and last is not None and last.ref_kf_id is not None:
            # the last frame became the keyframe the merge moved (a merge follows a keyframe): its pose is that
            # keyframe's (ORB-SLAM UpdateLastFrame: Tlr of a keyframe's own frame is the identity), not the old one
            ref = last.ref_kf_id
            if self.store.has_keyframe(ref):
                kf = self.store.get_keyframe(ref)
                if kf.frame_index == last.index and kf.timestamp_s == last.timestamp_s:
                    self._last_T_l_r = np.eye(4)
        for name in ("velocity", "_last_T_l_r"):
            T = getattr(self, name)
            if T is not None:
                T = T.copy()
                T[:3, 3] *= scale
                setattr(self, name, T)

    def reset(self) -> None:
        """Erase the active map's keyframes (from the map and the keyframe database) and start initialising again
        (ORB-SLAM3 ResetActiveMap). Called by the runner when an outcome asks for it (``lost_decision ==
        RESET_MAP``), with local mapping and loop closing parked."""
        self.atlas.reset_active()
        self._restart()

    def start_new_map(self) -> None:
        """Keep the active map in the Atlas and initialise a new active map (ORB-SLAM3 CreateMapInAtlas). Called by
        the runner when an outcome asks for it (``lost_decision == NEW_MAP``), with local mapping and loop closing
        parked."""
        self.atlas.create_map()
        self._restart()

    def _restart(self) -> None:
        """Tracking's state after the active map was reset or replaced: initialise again."""
        self._lost_since_s = None
        self._new_map_pending = False  # a session's map, if still to be made, is this one
        self._loaded_map_id = None
        with self._moved_lock:
            self._moved_scale = 1.0  # moves of the previous map do not concern the new one
        self.refiner = PoseRefiner(self.cfg, self.store, self.optimize_pose)  # reads the (new) active map's points
        self.state = TrackingState.NOT_INITIALIZED
        self._init_frame_index = None
        self.init.reset()
        self.last_frame = None
        self.velocity = None
        self.reference_kf_id = None

    # ---- a new session on a loaded Atlas ------------------------------------------------------------------

    def _relocalize_in_loaded_map(
        self, frame: Frame, timings: dict[str, float], mapping: MappingState
    ) -> TrackingOutcome:
        """A frame of a session on a loaded Atlas whose own map is not initialised yet (``reloc_or_new_map``):
        relocalization in the loaded active map, then its local map, as on any lost frame of it. On success the
        session goes on in that map (no new map is made); else the caller hands the frame to the new map's
        initialisation."""
        self.state = TrackingState.LOST
        outcome = self._track(frame, timings, mapping)
        if outcome.state == TrackingState.OK:
            log.info(
                "frame %d relocalized in the loaded map %d: the session goes on in it (no new map)",
                frame.index,
                self.atlas.active_id,
            )
            self._loaded_map_id = None
            self._new_map_pending = False
            self.init.reset()
        return outcome

    def _make_session_map(self) -> None:
        """The session's own map, made when its initialisation is about to write it (ORB-SLAM3 LoadAtlas +
        CreateNewMap): the loaded active map stays in the Atlas, to be joined by map merging."""
        if not self._new_map_pending:
            return
        loaded = self.atlas.active_id
        self.atlas.create_map()
        self.refiner = PoseRefiner(self.cfg, self.store, self.optimize_pose)
        self._new_map_pending = False
        self._loaded_map_id = None
        log.info(
            "a new map %d starts for this session; the loaded map %d stays in the Atlas", self.atlas.active_id, loaded
        )

    # ---- initialisation ------------------------------------------------------------------------

    def _initialize(self, frame: Frame) -> TrackingOutcome:
        if frame.features.bf > 0.0:
            return self._initialize_stereo(frame)
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
        self._make_session_map()
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
        self._init_frame_index = frame.index
        self.last_frame = frame
        self.velocity = None
        self.state = TrackingState.OK
        self.init.reset()
        outcome.state = TrackingState.OK
        outcome.T_c_w = frame.T_c_w.copy()
        outcome.inliers = kf_cur.n_tracked_points()
        outcome.new_keyframes = [kf_ini, kf_cur]
        outcome.initialized_map = True
        outcome.keyframe = KeyFrameDecision.INSERT
        outcome.reference_kf_id, outcome.T_ref_w = kf_cur.id, kf_cur.T_c_w
        outcome.message = f"initialised ({attempt.result.model}, {attempt.matches} matches)"
        return outcome

    def _initialize_stereo(self, frame: Frame) -> TrackingOutcome:
        """ORB-SLAM2 Tracking::StereoInitialization (stereo and RGB-D): a frame with more than
        ``stereo_init_min_features`` keypoints becomes the map's first keyframe at the origin, with a map point for
        every keypoint that has a depth (close or far), back-projected at it; metric scale from the sensor."""
        outcome = TrackingOutcome(
            frame.index, frame.timestamp_s, TrackingState.NOT_INITIALIZED, None, len(frame.features), 0, "initialize"
        )
        n = len(frame.features)
        if n <= self.cfg.stereo_init_min_features:
            outcome.message = f"only {n} features (stereo initialisation needs > {self.cfg.stereo_init_min_features})"
            return outcome
        frame.T_c_w = np.eye(4)
        self._make_session_map()
        kf = create_stereo_initial_map(self.store, frame)
        # a two-camera frame: each stereo point at both of its keypoints (ORB-SLAM3 StereoInitialization, Nleft)
        frame.point_ids = with_stereo_partners(frame.features, kf.point_ids)
        frame.ref_kf_id = kf.id
        self.reference_kf_id = kf.id
        self.last_kf_frame_index = frame.index
        self.last_frame = frame
        self._last_T_l_r = None
        self.velocity = None
        self.state = TrackingState.OK
        outcome.state = TrackingState.OK
        outcome.T_c_w = frame.T_c_w.copy()
        outcome.inliers = kf.n_tracked_points()
        outcome.new_keyframes = [kf]
        outcome.initialized_map = True
        outcome.keyframe = KeyFrameDecision.INSERT
        outcome.reference_kf_id, outcome.T_ref_w = kf.id, kf.T_c_w
        outcome.message = f"initialised from one frame ({outcome.inliers} points with depth)"
        log.info("map initialised from frame %d (stereo/RGB-D): %d points", frame.index, outcome.inliers)
        return outcome

    # ---- tracking --------------------------------------------------------------------------------

    def _track(self, frame: Frame, timings: dict[str, float], mapping: MappingState) -> TrackingOutcome:
        """V-B..E on a frame of an initialised map, under the map's read lock from the first pose read to the
        outcome (ORB-SLAM's Tracking::Track holds mMutexMapUpdate throughout): a merge moving the map comes wholly
        before or wholly after the frame, whose poses, reference keyframe pose and new keyframe agree."""
        with self.store.read():
            moves_seen = self._n_moves()
            outcome = self._track_locked(frame, timings, mapping)
        outcome.map_moves = moves_seen
        return outcome

    def _track_locked(self, frame: Frame, timings: dict[str, float], mapping: MappingState) -> TrackingOutcome:
        cfg = self.cfg
        store = self.store
        t0 = time.perf_counter()
        with store.read():
            self._apply_map_moves()
            method = "lost"
            ok = False
            why: list[str] = []  # what failed, for the frame's message when tracking is lost
            self._frame_bow = None
            if self.state == TrackingState.LOST:
                method = "relocalization"
                ok = self._relocalize(frame)
                if not ok:
                    why.append("relocalization: no candidate keyframe gave a pose with enough inliers")
                elif self.localization_only:
                    self._vo = False  # the map is tracked again (ORB-SLAM2 keeps mbVO here: module docstring)
            elif self.state == TrackingState.OK and self.last_frame is not None and self.localization_only:
                last = self.last_frame
                update_last_frame(store, last, self._last_T_l_r)
                ok, method = self._localization_initial_pose(frame, last, why)
            elif self.state == TrackingState.OK and self.last_frame is not None:
                last = self.last_frame
                update_last_frame(store, last, self._last_T_l_r)
                if self.velocity is not None:
                    ok = track_with_motion_model(frame, last, self.velocity, store, cfg, self.refiner)
                    method = "motion_model"
                    if not ok:
                        why.append(f"motion model: {np.count_nonzero(frame.point_ids >= 0)} matches/inliers left")
                if not ok:
                    ok = self._track_reference_keyframe(frame, last, why)
                    method = "reference_keyframe"
            t1 = time.perf_counter()
            inliers = 0
            if ok and self.localization_only and self._vo:
                # ORB-SLAM2: "few matches to MapPoints in the map. We cannot retrieve a local map": the motion model's
                # pose, no TrackLocalMap until a relocalization succeeds
                inliers = int(np.count_nonzero(frame.point_ids >= 0))
            elif ok:
                since_reloc = frame.index - self.last_reloc_frame_index
                wide = since_reloc < cfg.local_map_wide_search_frames_after_reloc
                inliers, reference = track_local_map(frame, store, cfg, self.refiner, wide)
                if reference is not None:
                    self.reference_kf_id = reference
                recent_reloc = since_reloc < self.max_frames  # code (TrackLocalMap): mnLastRelocFrameId + mMaxFrames
                needed = cfg.min_local_map_inliers_after_reloc if recent_reloc else cfg.min_local_map_inliers
                ok = inliers >= needed
                if not ok:
                    why.append(f"local map: {inliers} inliers < {needed}")
            t2 = time.perf_counter()
        timings["initial_pose_ms"] = (t1 - t0) * 1e3
        timings["local_map_ms"] = (t2 - t1) * 1e3
        if not ok:
            return self._lost(frame, method, "; ".join(why))
        assert frame.T_c_w is not None
        self._lost_since_s = None
        self.velocity = None if method == "relocalization" else velocity(frame, self.last_frame)
        self.state = TrackingState.OK
        frame.point_ids[frame.outlier] = -1
        frame.outlier[:] = False
        frame.ref_kf_id = self.reference_kf_id
        outcome = TrackingOutcome(
            frame.index, frame.timestamp_s, TrackingState.OK, frame.T_c_w.copy(), len(frame.features), inliers, method
        )
        if self.localization_only:
            outcome.keyframe = KeyFrameDecision.NOT_NEEDED  # ORB-SLAM NeedNewKeyFrame: mbOnlyTracking -> false
        else:
            outcome.keyframe = decide_keyframe(self._keyframe_facts(frame, inliers, mapping), cfg)
        if outcome.keyframe == KeyFrameDecision.INSERT:
            kf = self._new_keyframe(frame)
            outcome.new_keyframes = [kf]
            outcome.reference_kf_id, outcome.T_ref_w = kf.id, kf.T_c_w
        else:
            self.last_frame = frame
            self._last_T_l_r = pose_relative_to_reference(store, frame)
            ref = self.reference_kf_id
            with store.read():
                if ref is not None and store.has_keyframe(ref):
                    outcome.reference_kf_id, outcome.T_ref_w = ref, store.get_keyframe(ref).T_c_w
        return outcome

    def _track_reference_keyframe(self, frame: Frame, last: Frame, why: list[str]) -> bool:
        """V-B's second case (TrackReferenceKeyFrame), from the last frame's pose; says why it failed in ``why``."""
        assert last.T_c_w is not None
        ok = track_reference_keyframe(
            frame,
            self.reference_kf_id,
            last.T_c_w,
            self.store,
            self.cfg,
            self.refiner,
            self.place,
            self._frame_bow_of(frame),
        )
        if not ok:
            why.append(f"reference keyframe: {np.count_nonzero(frame.point_ids >= 0)} matches/inliers left")
        return ok

    def _localization_initial_pose(self, frame: Frame, last: Frame, why: list[str]) -> tuple[bool, str]:
        """The initial pose in localization mode (ORB-SLAM2 Tracking::Track, mbOnlyTracking, state OK): returns
        (success, method). mbVO false: the motion model alone, or the reference keyframe without a velocity. mbVO
        true: the motion model and relocalization both; relocalization's pose wins when it succeeds (mbVO cleared),
        else the motion model's is kept (its matched points' found counters raised, ORB-SLAM2's IncreaseFound)."""
        store = self.store
        if not self._vo:
            if self.velocity is not None:
                ok = self._localization_motion_model(frame, last)
                if not ok:
                    why.append(f"motion model: {np.count_nonzero(frame.point_ids >= 0)} inliers left")
                return ok, "motion_model"
            return self._track_reference_keyframe(frame, last, why), "reference_keyframe"
        ok_mm = False
        by_mm: tuple[F64 | None, NDArray[np.int64], NDArray[np.bool_]] | None = None
        if self.velocity is not None:
            ok_mm = self._localization_motion_model(frame, last)
            by_mm = (None if frame.T_c_w is None else frame.T_c_w.copy(), frame.point_ids.copy(), frame.outlier.copy())
        ok_reloc = self._relocalize(frame)
        if ok_reloc:
            self._vo = False
            return True, "relocalization"
        if ok_mm and by_mm is not None:
            frame.T_c_w, frame.point_ids, frame.outlier = by_mm
            if self._vo:
                found = frame.point_ids[(frame.point_ids >= 0) & ~frame.outlier]
                store.increase_found(found[store.has_points(found)])
            return True, "motion_model"
        why.append("visual odometry: neither the motion model nor relocalization gave a pose")
        return False, "motion_model"

    def _localization_motion_model(self, frame: Frame, last: Frame) -> bool:
        """ORB-SLAM2 TrackWithMotionModel in localization mode: success with more than
        ``localization_min_motion_model_inliers - 1`` inliers after the pose optimization (visual-odometry matches
        counted), and mbVO set when fewer than ``min_inliers_after_pose_opt`` of them are on map points (points some
        keyframe observes)."""
        assert self.velocity is not None
        track_with_motion_model(frame, last, self.velocity, self.store, self.cfg, self.refiner)
        matched = frame.point_ids[frame.point_ids >= 0]
        in_map = matched[self.store.has_points(matched)]
        n_map = int(np.count_nonzero(self.store.point_rows(in_map, "n_observations") > 0)) if in_map.size else 0
        self._vo = n_map < self.cfg.min_inliers_after_pose_opt
        return int(matched.size) >= self.cfg.localization_min_motion_model_inliers

    def _new_keyframe(self, frame: Frame) -> KeyFrame:
        """The keyframe made from the tracked frame (put in the map by local mapping); it becomes the reference."""
        kf = new_keyframe(self.store, frame, frame.point_ids)
        self.reference_kf_id = kf.id
        frame.ref_kf_id = kf.id
        self.last_kf_frame_index = frame.index
        self.last_frame = frame
        self._last_T_l_r = pose_relative_to_reference(self.store, frame)  # None: not in the map yet
        return kf

    def _keyframe_facts(self, frame: Frame, inliers: int, mapping: MappingState) -> KeyFrameFacts:
        """The numbers of V-E's conditions, read from the map under its read lock."""
        store = self.store
        with store.read():
            n_kfs = store.n_keyframes()
            n_ref: int | None = None
            if self.reference_kf_id is not None and store.has_keyframe(self.reference_kf_id):
                ref = store.get_keyframe(self.reference_kf_id)
                ref_ids = ref.point_ids[store.has_points(ref.point_ids)]
                if frame.features.bf > 0.0:  # stereo/RGB-D: ORB-SLAM's count, a stereo observation counting twice
                    n_obs = orbslam_observation_counts(store, ref_ids)
                else:
                    n_obs = store.point_rows(ref_ids, "n_observations") if ref_ids.size else np.zeros(0, np.int64)
                n_ref = int(np.count_nonzero(n_obs >= reference_min_observations(n_kfs, self.cfg)))
        feats = frame.features
        stereo = feats.bf > 0.0
        close_tracked = close_untracked = 0
        if stereo:
            close = feats.is_close()
            tracked = frame.point_ids >= 0
            close_tracked = int(np.count_nonzero(close & tracked))
            close_untracked = int(np.count_nonzero(close & ~tracked))
        return KeyFrameFacts(
            frame.index,
            self.last_kf_frame_index,
            self.last_reloc_frame_index,
            inliers,
            n_ref,
            n_kfs,
            mapping,
            self.max_frames,
            stereo,
            close_tracked,
            close_untracked,
        )

    def _relocalize(self, frame: Frame) -> bool:
        """V-C (needs the place recognizer); on success the keyframe it relocalized against becomes the reference."""
        if self.place is None:
            return False
        # candidates of every map, grouped in their own maps (Atlas.best_neighbors); only the active map's are tried
        # (ORB-SLAM3 DetectRelocalizationCandidates(F, pMap): pKFi->GetMap() != pMap -> skipped)
        kf_id = relocalize(
            frame,
            self._frame_bow_of(frame)(),
            self.store,
            self.place,
            self.cfg,
            self.refiner,
            self.atlas.best_neighbors,
            self.rng,
        )
        if kf_id is None:
            return False
        self.reference_kf_id = kf_id
        frame.ref_kf_id = kf_id
        self.last_reloc_frame_index = frame.index
        self.relocalizations += 1
        return True

    def _frame_bow_of(self, frame: Frame) -> Callable[[], BowDescription]:
        """The frame's bag of words, computed on first use (reference keyframe, relocalization)."""

        def bow() -> BowDescription:
            assert self.place is not None
            if self._frame_bow is None:
                self._frame_bow = self.place.transform(frame.features.descriptors)
            return self._frame_bow

        return bow

    def _lost(self, frame: Frame, method: str, why: str = "") -> TrackingOutcome:
        """The outcome of a frame tracking failed on; ``why``: what failed (said in the frame's message)."""
        self.state = TrackingState.LOST
        self.velocity = None
        msg = f"tracking lost at frame {frame.index} ({method}{': ' + why if why else ''})"
        if self._lost_since_s is None:
            self._lost_since_s = frame.timestamp_s
        n_kfs = self.store.n_keyframes()
        decision = decide_when_lost(LostRecord(n_kfs, frame.timestamp_s - self._lost_since_s), self.lost_policy)
        if decision == LostDecision.RESET_MAP:
            msg += f"; the map has {n_kfs} keyframes: reset and initialise again"
        elif decision == LostDecision.NEW_MAP:
            limit_s = self.lost_policy.time_recently_lost_s
            msg += f"; relocalization failed for {limit_s:g} s: the map ({n_kfs} keyframes) stays in the Atlas"
            msg += ", a new map starts"
        log.info(msg)
        return TrackingOutcome(
            frame.index,
            frame.timestamp_s,
            self.state,
            None,
            len(frame.features),
            0,
            method,
            message=msg,
            lost_decision=decision,
        )

    def _bounds_of(self, camera: Camera) -> ImageBounds:
        key = id(camera)
        if key not in self._bounds:
            self._bounds[key] = ImageBounds.of(camera)
        return self._bounds[key]
