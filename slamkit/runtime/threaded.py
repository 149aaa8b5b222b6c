"""The real-time runner: tracking, local mapping and loop closing in three threads, as ORB-SLAM runs.

Tracking runs in the calling thread (so Ctrl-C lands there); a frame-source thread plays the dataset (as fast as
possible, or at its own frame rate with dropped frames counted; a live source such as ``dataset=camera`` always in
real time, read continuously, its first Ctrl-C ending the run as an end of stream would); local mapping and loop
closing are PipelineWorkers. Each decision has one owner:

- Tracking is given local mapping's state as data each frame (``MappingState``: idle? accepting keyframes — not
  while parked for a loop correction?) and decides about keyframes; the runner hands the keyframes it made to local
  mapping (setting its abort token so a running local BA stops early, ORB-SLAM V-E). When tracking wants a keyframe
  but local mapping is busy (``KeyFrameDecision.MAPPING_BUSY``), the runner acts: in real time it stops the running
  local BA and no keyframe is made (ORB-SLAM); playing as fast as possible it waits for local mapping, then has the
  tracker make the keyframe (docs/runtime.md).
- Local mapping inserts every keyframe into the map (slamkit/pipeline/keyframe_insertion.py) and hands it to loop
  closing. Frames are recorded against the reference keyframe's pose their outcome carries, so the runner never
  needs a keyframe local mapping has not inserted yet.
- Loop closing detects loops while local mapping goes on (the keyframes it uses are pinned so culling leaves them);
  only the correction of an accepted loop parks local mapping at a safe point (a Future), after its queue, so a
  correction (under the map's write lock, bumping the map epoch) never meets a half-done local-mapping step.
- A map reset or a new map tracking asks for (``TrackingOutcome.lost_decision`` RESET_MAP / NEW_MAP, ORB-SLAM3's
  lost policy) is carried out here: both workers are parked and emptied, then ``Tracker.reset`` /
  ``Tracker.start_new_map`` changes the Atlas's active map.

Any thread's exception stops the run: tracking stops taking frames, the other workers stop, and ``run`` raises
PipelineThreadError naming the thread with its traceback; ``self.log`` and ``self.recorder`` keep everything done so
far, and ``slamkit_run_finished`` still fires, so the outputs plugin writes it. Lifecycle hooks run on a fourth
thread, the event dispatcher's (slamkit/runtime/events.py): the pipeline threads only queue their events, so a
listener's cost never lands on tracking. Not deterministic (thread timing decides which frames become keyframes); the
SequentialRunner is the reproducible mode.
"""

from __future__ import annotations

import contextlib
import logging
import math
import signal
import threading
import time
import traceback
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

from tqdm import tqdm

from slamkit.errors import ConfigError
from slamkit.interfaces import Camera, Dataset, MapStore
from slamkit.map.atlas import Atlas, MapChange
from slamkit.map.entities import KeyFrame
from slamkit.pipeline.local_mapping import LocalMapper
from slamkit.pipeline.loop_closing import LoopCloser, MapMerge
from slamkit.pipeline.lost import LostDecision
from slamkit.pipeline.outcomes import KeyFrameDecision, MappingState, TrackingOutcome, TrackingState
from slamkit.pipeline.startup import thaw_startup_heap
from slamkit.pipeline.tracking import Tracker
from slamkit.pipeline.trajectory import KeptFrames, TrajectoryRecorder
from slamkit.runtime.events import EventDispatcher, RunEvents
from slamkit.runtime.extract_ahead import ExtractedAhead
from slamkit.runtime.log import RunLog, log_tracking_outcome, map_frames
from slamkit.runtime.modelled_mapping import modelled_mapping
from slamkit.runtime.priority import gil_switch_interval, lower_process_priority
from slamkit.runtime.source import (
    CAMERA_BUFFER_FRAMES,
    END,
    PREFETCH_FRAMES,
    FrameSource,
    check_bad_frames_policy,
    frame_count,
    is_live,
    readable_frames,
)
from slamkit.runtime.workers import PipelineThreadError, PipelineWorker, ThreadFault, raised_by_ctrl_c
from slamkit.sensors import FrameData, FrameRecords

log = logging.getLogger("slamkit.runner")

#: How long the end of a run waits for a worker thread to finish its queue / to stop after a failure, s.
DRAIN_TIMEOUT_S = 600.0
STOP_TIMEOUT_S = 60.0
#: How long the end of a live run waits for the frame source to release its device (a blocked read gives up after
#: the dataset's read_timeout_s), s.
SOURCE_JOIN_TIMEOUT_S = 10.0
#: ``RunLog.source_end`` of a live run Ctrl-C ended.
CTRL_C = "Ctrl-C"
#: ``runner.frame_waits_for``: what a monocular frame waits for, as fast as possible, before it is tracked
FRAME_WAITS_FOR_LOCAL_MAPPING = "local_mapping"
FRAME_WAITS_FOR = (FRAME_WAITS_FOR_LOCAL_MAPPING, "none")


class ThreadedRunner:
    """Runs a dataset through tracking, local mapping and loop closing in three threads.

    realtime: play frames at the dataset's timestamps (scaled by ``speed``) and drop those that arrive while
    tracking is busy; otherwise every frame is tracked as fast as possible.
    preload: read (or render) every frame into memory before playback starts, so playback costs no CPU, as a
    camera's frames do not (the memory is reported as ``log.preloaded_mb``).
    background_niceness: in real-time playback, how much local mapping, loop closing and a background optimizer
    process lower their scheduling priority, so tracking gets the cores first (slamkit/runtime/priority.py; 0:
    equal priority). Not applied when playing as fast as possible (see ``run``).
    gil_switch_interval_s: the interpreter's GIL switch interval during the run (None: unchanged).
    events: fires the plugins' lifecycle hooks, from its own thread (None: nobody listens).
    """

    def __init__(
        self,
        tracker: Tracker,
        mapper: LocalMapper | None,
        atlas: Atlas,
        progress: bool = True,
        loop_closer: LoopCloser | None = None,
        realtime: bool = False,
        speed: float = 1.0,
        preload: bool = False,
        background_niceness: int = 0,
        gil_switch_interval_s: float | None = None,
        events: EventDispatcher | None = None,
        bad_frames: str = "skip",
        modelled_mapping_ms: float = 0.0,
        modelled_mapping_new_map_ms: float | None = None,
        wait_for_local_mapping: bool = True,
        frame_waits_for: str = FRAME_WAITS_FOR_LOCAL_MAPPING,
        extract_ahead: int = 0,
        realtime_extract_ahead: bool = False,
        extract_ahead_single_threaded: bool = False,
        realtime_extract_single_threaded: bool = True,
        realtime_extract_ahead_init: bool = False,
        realtime_camera_buffer: int = CAMERA_BUFFER_FRAMES,
    ) -> None:
        """mapper: local mapping (None: localization only, ``mode=localization``: no local mapping thread, no loop
        closing, tracking makes no keyframe). bad_frames: what to do with a frame the dataset cannot read, "skip"
        (logged and reported) or "stop" (slamkit.runtime.source.readable_frames). modelled_mapping_ms /
        modelled_mapping_new_map_ms: as fast as possible only (not ``realtime``), local mapping's modelled time per
        keyframe in sequence time, ms (:class:`~slamkit.runtime.modelled_mapping.ModelledMapping`): a monocular frame
        within it of the last keyframe makes no keyframe, as in ORB-SLAM at a camera's rate; 0: the runner waits for
        local mapping whenever tracking wants a keyframe. wait_for_local_mapping: as fast as possible only; False:
        never wait — a monocular frame that wants a keyframe while local mapping is busy interrupts its local BA and
        makes none, as ORB-SLAM2/3's released code fed as fast as it tracks (the modelled mapping time is then not
        used: the thread's own state decides, as in real time).
        frame_waits_for: as fast as possible with ``wait_for_local_mapping``, monocular frames only, what a frame
        waits for once its features are extracted, before it is tracked: "local_mapping" — local mapping is done with
        every keyframe handed to it (the sequential runner's map, hence its keyframe decisions; with the modelled
        mapping time, the sequential runner's with the same model); "none" — nothing (docs/runtime.md).
        extract_ahead: as fast as possible only, the frames the frame source reads and extracts features of ahead of
        tracking (slamkit/runtime/extract_ahead.py: the same records, made on the core local mapping leaves idle);
        0: tracking extracts each frame itself. realtime_extract_ahead: in real time, the frame source extracts each
        frame's features as it releases it (while tracking works on the one before), before the mailbox.
        extract_ahead_single_threaded: as fast as possible, the extractions ahead keep their work in the frame-source
        thread (slamkit.thread_budget; the ORB extractor's level threads are not used): they run beside local
        mapping, which every frame after a keyframe waits for. Real time: not used.
        realtime_extract_single_threaded: in real time with ``realtime_extract_ahead``, the same for the frame source's
        extractions: one core extracts while tracking, at a higher priority than local mapping
        (``background_niceness``), would otherwise take both cores from local mapping for every frame's extraction.
        realtime_extract_ahead_init: with ``realtime_extract_ahead``, the frames of a monocular initialisation are
        extracted ahead too, with the initialisation extractor (the same records; tracking then spends only the
        initialisation attempt on each); False: tracking extracts them itself.
        realtime_camera_buffer: in paced real time, the frames the camera holds while the frame source is busy with
        one (its extraction ahead running late); older ones are dropped unprepared (slamkit/runtime/source.py)."""
        if extract_ahead < 0:
            raise ConfigError(f"runner.extract_ahead = {extract_ahead}: expected a number of frames >= 0 (0: off)")
        self.extract_ahead = int(extract_ahead)
        self.realtime_extract_ahead = bool(realtime_extract_ahead)
        self.extract_ahead_single_threaded = bool(extract_ahead_single_threaded)
        self.realtime_extract_single_threaded = bool(realtime_extract_single_threaded)
        self.realtime_extract_ahead_init = bool(realtime_extract_ahead_init)
        self.realtime_camera_buffer = int(realtime_camera_buffer)
        self._ahead: ExtractedAhead | None = None
        if frame_waits_for not in FRAME_WAITS_FOR:
            raise ConfigError(
                f"runner.frame_waits_for = {frame_waits_for!r}: expected one of {', '.join(FRAME_WAITS_FOR)}"
            )
        self.modelled_mapping = modelled_mapping(modelled_mapping_ms, modelled_mapping_new_map_ms)
        if not wait_for_local_mapping and self.modelled_mapping.enabled:
            # tracking never waits: local mapping's real state decides, as in real time (the model stands in for a
            # camera's frame period only when frames wait for local mapping)
            log.info(
                "runner.wait_for_local_mapping=false: runner.modelled_mapping_ms=%g is not used (the local mapping "
                "thread's own state decides)",
                modelled_mapping_ms,
            )
            self.modelled_mapping = modelled_mapping(0.0, 0.0)
        self.wait_for_local_mapping = wait_for_local_mapping
        self.frame_waits_for = frame_waits_for
        self.tracker = tracker
        self.mapper = mapper
        self.loop_closer = loop_closer
        self.atlas = atlas
        self.recorder = TrajectoryRecorder()
        #: the frames of the Atlas's maps the recorder does not hold (earlier sessions', other maps'): map_frames()
        self.kept_frames = KeptFrames(getattr(atlas, "loaded_frames", None) or {})
        self.progress = progress
        self.realtime = realtime
        self.speed = speed
        self.preload = preload
        self.background_niceness = background_niceness
        self.gil_switch_interval_s = gil_switch_interval_s
        self.bad_frames = check_bad_frames_policy(bad_frames)
        self._modelled_busy = False  # the frame being tracked saw local mapping busy by the model, not by the thread
        # how long the frame being tracked waited for local mapping before it was tracked (the model's end of mapping,
        # or frame_waits_for), ms
        self._pre_track_wait_ms = 0.0
        self._depth_frames = False  # the frames tracked so far carry depth (stereo/RGB-D: the model does not apply)
        self.log = RunLog(runner="threaded")
        self.events = events
        self._run_events = RunEvents(None, "threaded", atlas)
        self._fault: ThreadFault | None = None
        self._fault_lock = threading.Lock()
        self._source: FrameSource | None = None
        self._mapping: PipelineWorker[KeyFrame] | None = None
        self._closing: PipelineWorker[KeyFrame] | None = None
        self.mapping_parks_for_loops = 0  # times loop closing parked local mapping (once per loop correction)
        # a run whose frames the caller hands in (begin / step / end)
        self._live_stack = contextlib.ExitStack()
        self._live_workers: list[PipelineWorker[KeyFrame]] = []
        self._live_start = time.perf_counter()
        self._live_first_t: float | None = None

    def map_frames(self) -> dict[int, FrameRecords]:
        """map id -> every frame of that map, this run's and the earlier sessions' a loaded map file kept, each
        relative to a keyframe the map has now (slamkit.runtime.log.map_frames): what ``map.save`` writes."""
        return map_frames(self.atlas, self.recorder, self.kept_frames)

    @property
    def store(self) -> MapStore:
        """The active map of the Atlas."""
        return self.atlas.active

    # ---- faults ------------------------------------------------------------------------------------

    def _on_fault(self, fault: ThreadFault) -> None:
        """Called from the failing thread: remember the first fault and stop every other thread."""
        with self._fault_lock:
            if self._fault is not None:
                return
            self._fault = fault
            self.log.failed_thread = fault.thread_name
        log.error("the %s thread failed: %s", fault.thread_name, fault.exc)
        if self._source is not None and fault.thread_name != self._source.name:
            self._source.interrupt()  # a failed source still delivers the frames it read, then the end
        for worker in (self._mapping, self._closing):
            if worker is not None and worker.name != fault.thread_name:
                worker.stop(drain=False)

    # ---- worker bodies --------------------------------------------------------------------------------

    def _map_keyframe(self, kf: KeyFrame, abort: threading.Event) -> None:
        """Local mapping thread: one keyframe (VI-A..E), then hand it to loop closing."""
        assert self._mapping is not None and self.mapper is not None
        if self._mapping.pending() > 0:
            abort.set()  # ORB-SLAM skips local BA while newer keyframes wait
        t_start = time.perf_counter()
        outcome = self.mapper.step(kf, abort=abort)
        self.log.mapping.append(outcome)
        if "local_ba_ms" in outcome.timings_ms:
            # the stages ran in the order of their timings: the BA began after the ones listed before it
            stages = list(outcome.timings_ms)
            before = sum(outcome.timings_ms[k] for k in stages[: stages.index("local_ba_ms")])
            ba_start = t_start + before / 1e3
            self.log.local_ba_wall_s.append((ba_start, ba_start + outcome.timings_ms["local_ba_ms"] / 1e3))
        for culled in outcome.culled_keyframes:
            self.recorder.on_culled(culled)
            self.kept_frames.on_culled(self.atlas.active_id, culled)
        self._run_events.keyframe_mapped(outcome)
        if self._closing is not None and self.store.has_keyframe(kf.id):
            self._closing.submit(kf)

    def _close_loops(self, kf: KeyFrame, abort: threading.Event) -> None:
        """Loop closing thread: detect a loop at one keyframe while local mapping goes on; only the correction of
        an accepted loop parks local mapping (after its queue: every keyframe is in the map the correction moves),
        as ORB-SLAM's CorrectLoop requests local mapping to stop."""
        assert self.loop_closer is not None
        detection = self.loop_closer.detect(kf)  # culled meanwhile: the outcome says so
        outcome = detection.outcome
        if detection.loop is not None or detection.merge is not None:
            # a global BA still running from the last loop stops first (ORB-SLAM2 CorrectLoop: mbStopGBA); it may
            # be waiting to park local mapping itself, so not while local mapping is parked here
            global_ba_stopped = self.loop_closer.abort_global_ba()
            try:
                # a merge parks local mapping as a loop correction does (ORB-SLAM3 MergeLocal: RequestStop);
                # tracking goes on, waiting only while the merge writes the map
                with self._parked(self._mapping, finish_queue=True):
                    self.mapping_parks_for_loops += 1
                    if detection.merge is not None:
                        # ORB-SLAM3 bRelaunchBA: the global BA stopped here runs again on the merged map
                        outcome = self.loop_closer.merge(detection, global_ba_stopped=global_ba_stopped)
                    else:
                        outcome = self.loop_closer.correct(detection)
            finally:
                self.loop_closer.release(detection)
        self.log.loops.append(outcome)
        self._run_events.loop_checked(outcome)

    def _on_merge(self, merge: MapMerge) -> None:
        """Loop closing (its thread, the active map's write lock held) moves the active map into another map's frame
        to merge them: the frames recorded relative to the moved keyframes follow the move's scale (a frame tracked
        before the move and not yet recorded follows it in ``_track``: Tracker.follow_map_moves);
        slamkit_maps_merged is queued."""
        self.recorder.rescale(merge.moved_kf_ids, merge.G.s)
        self.kept_frames.merged(merge.into_map_id, merge.merged_map_id, merge.moved_kf_ids, merge.G.s)
        self.tracker.map_moved(merge.G)  # the motion model's velocity follows the move's scale
        self.log.maps_merged += 1
        self._run_events.maps_merged(
            merge.kf_id, merge.matched_kf_id, merge.merged_map_id, merge.into_map_id, merge.G.matrix()
        )

    @contextlib.contextmanager
    def _parked(self, *workers: PipelineWorker[KeyFrame] | None, finish_queue: bool = False) -> Iterator[None]:
        """Park workers at a safe point for the duration of the block (raises if one of them died); with
        finish_queue they first process what is queued."""
        parked = []
        try:
            for worker in workers:
                if worker is None:
                    continue
                worker.pause(finish_queue).result()
                parked.append(worker)
            yield
        finally:
            for worker in parked:
                worker.resume()

    @contextlib.contextmanager
    def _quiesced_for_reset(self) -> Iterator[None]:
        """Tracking resets the active map or starts a new one: park both workers and drop their queued keyframes
        first (no keyframe of the old map reaches the new one)."""
        if self.loop_closer is not None:
            self.loop_closer.abort_global_ba()
        with self._parked(self._closing, self._mapping):
            for worker in (self._mapping, self._closing):
                if worker is not None:
                    dropped = worker.clear()
                    if dropped:
                        log.info("active map change: %s dropped %d queued keyframes", worker.name, dropped)
            yield

    # ---- tracking (the calling thread) --------------------------------------------------------------

    def _mapping_state(self, timestamp_s: float) -> MappingState:
        """Local mapping's state for the tracker (ORB-SLAM AcceptKeyFrames / isStopped || stopRequested) at a frame
        captured at ``timestamp_s`` (s); as fast as possible the runner waits for a busy local mapping
        (``waits_for_idle``), as a camera's frame period would give it time to finish — unless the modelled mapping
        time (``modelled_mapping_ms``) says a camera's frame would still find it busy: then it is busy, and a
        monocular frame makes no keyframe, as in ORB-SLAM; a frame past the modelled time first waits for the thread
        to finish the keyframes made so far (``_pre_track_wait_ms``), as a camera's frame would find them mapped.
        With or without the model, a monocular frame first waits for what ``frame_waits_for`` says (called by the
        tracker once the frame's features are extracted: ``_frame_waits``): with ``local_mapping`` every frame, inside
        the modelled time or past it, is tracked on the map local mapping finished, as the sequential runner's frame
        is. Without local mapping (localization only) it accepts nothing, as ORB-SLAM's stopped local mapping."""
        self._modelled_busy = False
        self._pre_track_wait_ms = 0.0
        if self._mapping is None:
            return MappingState(idle=False, accepting_keyframes=False)
        if self._frame_waits() and not self._mapping.idle():
            # the map local mapping finished, as the sequential runner's frame sees it (frame_waits_for)
            t0 = time.perf_counter()
            self._mapping.wait_idle()
            self._pre_track_wait_ms = (time.perf_counter() - t0) * 1e3
        stopping = self._mapping.stopping()
        if not self.realtime and not self._depth_frames and self.modelled_mapping.enabled:
            if not self.modelled_mapping.state(timestamp_s).idle:
                self._modelled_busy = True
                return MappingState(idle=False, accepting_keyframes=not stopping)
            if not stopping and not self._mapping.idle():
                # past the modelled end of the work on the keyframes made so far, a camera's frame would find local
                # mapping done with them (the sequential runner's model): the frame waits for the thread, so tracking
                # sees the map local mapping finished whatever the machine's speed or load
                t0 = time.perf_counter()
                self._mapping.wait_idle()
                self._pre_track_wait_ms = (time.perf_counter() - t0) * 1e3
                stopping = self._mapping.stopping()
        return MappingState(
            idle=self._mapping.idle() and not stopping,
            accepting_keyframes=not stopping,
            waits_for_idle=not self.realtime and self.wait_for_local_mapping,
        )

    def _keyframe_wanted_while_mapping_busy(self, out: TrackingOutcome) -> TrackingOutcome:
        """Tracking wants a keyframe but local mapping is busy (V-E condition 2 fails: ``out.keyframe`` is
        MAPPING_BUSY).

        Real time, or as fast as possible without ``wait_for_local_mapping``: stop the running local BA so mapping
        becomes free soon, and do not insert (ORB-SLAM: the next frames will ask again). As fast as possible: wait for local mapping to finish, then have the tracker
        make the keyframe, so tracking does not outrun mapping on a recorded sequence — a live camera gives mapping
        the time the frame period leaves it, and aborting every local BA because frames come faster than any camera
        would starve the map of its optimization. The wait is reported as ``mapping_wait_ms``."""
        assert self._mapping is not None
        if self._modelled_busy:  # busy in sequence time: no keyframe, as the sequential runner's model
            return out
        if self.realtime or not self.wait_for_local_mapping:
            self._mapping.abort.set()
            return out
        t0 = time.perf_counter()
        self._mapping.wait_idle()
        waited_ms = (time.perf_counter() - t0) * 1e3
        if self._fault is None and not self._mapping.stopping():
            out = self.tracker.make_keyframe(out)
        out.timings_ms["mapping_wait_ms"] = waited_ms
        if "track_ms" in out.timings_ms:  # the wait holds tracking: it is part of the frame's tracking time
            out.timings_ms["track_ms"] += waited_ms
        return out

    def _count_extraction_ahead(self, out: TrackingOutcome, data: FrameData) -> None:
        """A frame whose features were extracted ahead (in the frame source's thread): its ``extract_ms`` is that
        extraction's time, and ``track_ms`` counts it in place of the look-up tracking timed, so that the tracking
        time per frame stays the frame's whole cost, extraction included, as with tracking's own extraction."""
        served_ms = None if self._ahead is None else self._ahead.served_ms(data.index)
        if served_ms is None:
            return
        looked_up_ms = out.timings_ms.get("extract_ms", 0.0)
        out.timings_ms["extract_ms"] = served_ms
        if "track_ms" in out.timings_ms:
            out.timings_ms["track_ms"] += served_ms - looked_up_ms

    def _frame_waits(self) -> bool:
        """Whether the frame being tracked waits for local mapping after its extraction (``frame_waits_for``), with
        or without the modelled mapping time: the model then decides from the frame's timestamp whether local mapping
        is busy for the keyframe decision, on the map the thread finished (the sequential runner's model)."""
        return (
            self.frame_waits_for == FRAME_WAITS_FOR_LOCAL_MAPPING
            and self.wait_for_local_mapping
            and not self.realtime
            and not self._depth_frames
        )

    def _track(self, data: FrameData, camera: Camera) -> TrackingOutcome:
        map_before = self.atlas.active_id
        self._modelled_busy, self._pre_track_wait_ms = False, 0.0
        if self._frame_waits():
            # local mapping's state is read once the frame's features are extracted (the wait overlaps extraction)
            out = self.tracker.step(data, camera, lambda: self._mapping_state(data.timestamp_s))
        else:
            out = self.tracker.step(data, camera, self._mapping_state(data.timestamp_s))
            if self._pre_track_wait_ms > 0.0 and "track_ms" in out.timings_ms:
                # the frame waited for local mapping before it was tracked: part of its tracking time
                out.timings_ms["track_ms"] += self._pre_track_wait_ms
        if self._pre_track_wait_ms > 0.0:
            out.timings_ms["mapping_wait_ms"] = self._pre_track_wait_ms
        self._count_extraction_ahead(out, data)
        frame = self.tracker.current_frame
        if frame is not None and frame.index == out.frame_index:
            self._depth_frames = frame.features.bf > 0.0
        if out.keyframe == KeyFrameDecision.MAPPING_BUSY:
            out = self._keyframe_wanted_while_mapping_busy(out)
        self.modelled_mapping.keyframes_made(data.timestamp_s, len(out.new_keyframes), out.initialized_map)
        if out.lost_decision == LostDecision.RESET_MAP:
            with self._quiesced_for_reset():
                self.tracker.reset()
            self.modelled_mapping.reset()
        elif out.lost_decision == LostDecision.NEW_MAP:
            with self._quiesced_for_reset():
                self.tracker.start_new_map()
            self.modelled_mapping.reset()
        map_change = self.atlas.change_since(map_before)  # reset, or a new map with the old one kept
        map_was_reset = map_change == MapChange.RESET
        ref_id, T_ref_w = None, None
        # a merge may have moved the map since the frame was tracked (it takes the write lock): the outcome follows
        # the move, and no other move comes before its frame is recorded and its keyframe queued for local mapping
        with self.store.read():
            self.tracker.follow_map_moves(out)
            log_tracking_outcome(self.log, self.recorder, out, map_change, self.kept_frames, map_before)
            self._run_events.map_events(out)
            if out.new_keyframes and self._mapping is None:
                raise RuntimeError(f"frame {out.frame_index}: a keyframe was made in a run without local mapping")
            if out.new_keyframes and self._mapping is not None and not self._mapping.idle():
                self._mapping.abort.set()  # V-E: stop the running local BA so the new keyframe goes in soon
            for kf in out.new_keyframes:
                assert self._mapping is not None
                self._mapping.submit(kf)
            out.release_keyframes()  # local mapping has them; the log must not keep the culled ones alive
            if out.state == TrackingState.OK and out.T_c_w is not None and out.T_ref_w is not None:
                # recorded against the reference keyframe's pose as tracking read it (the frame's own pose when it
                # became that keyframe), so a keyframe local mapping has not inserted yet is never needed
                ref_id, T_ref_w = out.reference_kf_id, out.T_ref_w
                assert ref_id is not None
                self.recorder.record(out.frame_index, out.timestamp_s, out.T_c_w, ref_id, T_ref_w)
        self._run_events.frame_tracked(out, map_was_reset, ref_id, T_ref_w, data.image, self.tracker.current_frame)
        return out

    def run(
        self,
        dataset: Dataset,
        camera: Camera,
        on_frame: Callable[[TrackingOutcome], None] | None = None,
        run_dir: Path | None = None,
        config: Mapping[str, Any] | None = None,
    ) -> RunLog:
        """Process the dataset; results accumulate in ``self.log`` and ``self.recorder`` even if it raises.

        run_dir / config: where the run's files go and its resolved config, handed to the lifecycle hooks
        (``slamkit_run_started``; the built-in outputs plugin writes the run directory from its events).
        Raises PipelineThreadError when a pipeline thread failed; KeyboardInterrupt passes through after the
        threads stopped. ``slamkit_run_finished`` fires in every case, after the pipeline threads stopped. A live
        source (``dataset=camera``) is played in real time whatever ``realtime`` says; with ``preload`` it is a
        ConfigError.
        """
        if is_live(dataset):
            self._go_live(dataset)
        self._run_events = RunEvents(self.events, "threaded", self.atlas)
        self._run_events.started(dataset, run_dir, config, threaded=True)
        ended_by: BaseException | None = None
        try:
            self._run(dataset, camera, on_frame)
        except BaseException as exc:
            ended_by = exc
            raise
        finally:
            thaw_startup_heap()  # the warm-up froze the start-up heap for the run's duration only
            self._run_events.finished(self.log, ended_by)
        return self.log

    def _run(self, dataset: Dataset, camera: Camera, on_frame: Callable[[TrackingOutcome], None] | None = None) -> None:
        live = is_live(dataset)
        self._prepare(dataset, camera)
        readable = readable_frames(dataset, self.bad_frames, self._frame_skipped)
        frames: Iterable[FrameData] = self._preloaded(readable, len(dataset)) if self.preload else readable
        start = time.perf_counter()
        # a live device paces itself: read continuously (a file played as a stream is paced at its timestamps)
        paced = not live or bool(getattr(dataset, "paced", False))
        self._ahead = None
        if (self.extract_ahead > 0 and not self.realtime) or (self.realtime and self.realtime_extract_ahead):
            self._ahead = ExtractedAhead(
                self.tracker.frontend,
                camera,
                self.tracker.uses_tracking_extractor,
                single_threaded=(
                    self.realtime_extract_single_threaded if self.realtime else self.extract_ahead_single_threaded
                ),
                initialisation=self.realtime and self.realtime_extract_ahead_init,
            )
        self._source = FrameSource(
            frames,
            self.realtime,
            self._on_fault,
            self.speed,
            paced=paced,
            prepare=None if self._ahead is None else self._ahead.prepare,
            ahead=self.extract_ahead if self._ahead is not None and not self.realtime else PREFETCH_FRAMES,
            camera_buffer=self.realtime_camera_buffer,
        )
        workers = self._make_workers()
        bar = tqdm(total=frame_count(dataset), unit="frame", disable=not self.progress, dynamic_ncols=True)
        for thread in (self._source, *workers):
            thread.start()
        finished = False
        frontend = self.tracker.frontend
        try:
            if self._ahead is not None:
                self.tracker.frontend = self._ahead  # a FrontEnd by delegation (__getattr__)
            with gil_switch_interval(self.gil_switch_interval_s), self._ctrl_c_ends_stream(live):
                self._track_frames(camera, bar, on_frame)
            if self._fault is None:
                self._drain(workers)
            finished = True
        finally:
            self.tracker.frontend = frontend
            bar.close()
            if not finished or self._fault is not None:
                self._stop_all(workers)
            self._source.stop()
            if self._ahead is not None:
                log.info(
                    "features of %d frames extracted ahead of tracking, %d of them used (%s)",
                    self._ahead.extracted,
                    self._ahead.served,
                    "runner.realtime_extract_ahead" if self.realtime else f"runner.extract_ahead={self.extract_ahead}",
                )
                self._ahead = None
            if live:  # the source thread releases the device
                self._source.join(timeout=SOURCE_JOIN_TIMEOUT_S)
                self.log.source_end = self.log.source_end or getattr(dataset, "end_reason", None)
            self.log.frames_dropped = self._source.frames_dropped
            self.log.dropped_frames = list(self._source.dropped)
            if self._source.first_timestamp_s is not None and self._source.last_timestamp_s is not None:
                self.log.sequence_s = self._source.last_timestamp_s - self._source.first_timestamp_s
            self.log.wall_s = time.perf_counter() - start
            if self.realtime:
                self._log_playback()
        if self._fault is not None:
            raise self._fault.as_error()

    def _go_live(self, dataset: Dataset) -> None:
        """A live source is real time by nature: playback becomes real time (frames tracking has no time for are
        dropped, never queued); it cannot be preloaded (it has no end)."""
        if self.preload:
            raise ConfigError(
                f"runner.preload=true cannot preload the live source {getattr(dataset, 'name', '?')}: it has no end"
            )
        if not self.realtime:
            log.info("live source %s: real-time playback", getattr(dataset, "name", "?"))
            self.realtime = True
        self.log.source_end = None

    @contextlib.contextmanager
    def _ctrl_c_ends_stream(self, live: bool) -> Iterator[None]:
        """A live source has no end of its own: during its run the first Ctrl-C (SIGINT) ends the stream as an end of
        stream would — the frame taken is tracked, local mapping and loop closing finish their queues, the outputs are
        written, status "ok" with ``source_end`` "Ctrl-C"; a second Ctrl-C interrupts the run as Ctrl-C does on a
        recorded sequence. Only in the main thread (where Python delivers signals)."""
        if not live or threading.current_thread() is not threading.main_thread():
            yield
            return
        previous = signal.getsignal(signal.SIGINT)
        if previous is None:  # a handler not installed from Python cannot be put back: Python's own then
            previous = signal.default_int_handler

        def on_sigint(signum: int, frame: object) -> None:
            if self.log.source_end == CTRL_C or self._source is None:
                raise KeyboardInterrupt
            self.log.source_end = CTRL_C
            log.warning("Ctrl-C: the live run ends, its outputs are written (Ctrl-C again to interrupt it at once)")
            self._source.stop()

        signal.signal(signal.SIGINT, on_sigint)
        try:
            yield
        finally:
            signal.signal(signal.SIGINT, previous)

    def _log_playback(self) -> None:
        """The end-of-run account of real-time playback: frames tracked and dropped, tracking's median time per frame
        against the stream's frame period, the real-time factor, how a live stream ended."""
        tracked = len(self.log.tracking)
        dropped = self.log.frames_dropped
        share = 100.0 * dropped / max(tracked + dropped, 1)
        factor = self.log.realtime_factor
        track_ms = sorted((t1 - t0) * 1e3 for t0, t1 in self.log.tracking_wall_s)
        # the wall time between two frames: the stream's frame period over the playback speed when paced by the
        # runner (a live device paces itself: runner.speed does not apply)
        speed = self.speed if self._source is not None and self._source.paced else 1.0
        n_frames = tracked + dropped
        period_ms = 1e3 * self.log.sequence_s / (n_frames - 1) / speed if n_frames > 1 else math.nan
        late = self._source.frames_late if self._source is not None else 0
        log.info(
            "real-time playback: %d frames tracked, %d dropped (%.0f%%: %d came while tracking was busy, %d were "
            "replaced in the camera's buffer while the frame source extracted features ahead); tracking %.1f ms per "
            "frame (median) for a frame every %.1f ms; real-time factor %s (stream time over wall time)%s",
            tracked,
            dropped,
            share,
            dropped - late,
            late,
            track_ms[len(track_ms) // 2] if track_ms else math.nan,
            period_ms,
            "n/a" if factor is None else f"{factor:.2f}",
            "" if self.log.source_end is None else f"; the stream ended: {self.log.source_end}",
        )

    def _make_workers(self) -> list[PipelineWorker[KeyFrame]]:
        """Local mapping's and loop closing's workers (not started yet)."""
        # Only against a clock: playing as fast as possible, tracking is always runnable and would starve the
        # lower-priority local mapping, tracking on ahead of a map whose new points are not triangulated yet (the
        # room was lost at frame ~146 that way); with real-time playback tracking leaves time each frame period.
        nice = self.background_niceness if self.realtime else 0
        self._mapping = None
        if self.mapper is not None:  # None: localization only, tracking alone
            self._mapping = PipelineWorker("local-mapping", self._map_keyframe, self._on_fault, nice)
        if self.loop_closer is not None:
            self._closing = PipelineWorker("loop-closing", self._close_loops, self._on_fault, nice)
            # the global BA after a loop runs in its own thread, parking local mapping to write its result
            self.loop_closer.park_mapping = lambda: self._parked(self._mapping, finish_queue=True)
            self.loop_closer.on_merge = self._on_merge
        self._lower_optimizer_process_priority()
        return [w for w in (self._mapping, self._closing) if w is not None]

    # ---- frames handed in one by one (slamkit.api.System) -----------------------------------------------

    def begin(
        self, dataset: Dataset, camera: Camera, run_dir: Path | None = None, config: Mapping[str, Any] | None = None
    ) -> None:
        """Start a run whose frames the caller hands to ``step`` one by one (the caller's thread is the tracking
        thread; no frame source): fire ``slamkit_run_started`` (dataset: its name, length and ground truth for
        the listeners), load the compiled kernels, start local mapping and loop closing. Then ``end``."""
        self._run_events = RunEvents(self.events, "threaded", self.atlas)
        self._run_events.started(dataset, run_dir, config, threaded=True)
        self._live_stack = contextlib.ExitStack()
        self._live_first_t = None
        try:
            self.tracker.warm_up(camera)
            self._live_start = time.perf_counter()
            self._live_workers = self._make_workers()
            for worker in self._live_workers:
                worker.start()
            self._live_stack.enter_context(gil_switch_interval(self.gil_switch_interval_s))
        except BaseException as exc:
            self.end(exc)
            raise

    def step(self, data: FrameData, camera: Camera) -> TrackingOutcome:
        """Track one frame handed in by the caller (after ``begin``) and queue its keyframes for local mapping;
        returns what tracking did with it. Raises PipelineThreadError when local mapping or loop closing failed
        (the caller then ends the run with ``end``)."""
        if self._fault is not None:
            raise self._fault.as_error()
        t_track = time.perf_counter()
        try:
            out = self._track(data, camera)
        except Exception as exc:  # recorded like the run loop's tracking failure (failed_thread: tracking)
            if raised_by_ctrl_c(exc):
                raise KeyboardInterrupt from exc
            self._on_fault(ThreadFault("tracking", exc, traceback.format_exc()))
            raise
        self.log.tracking_wall_s.append((t_track, time.perf_counter()))
        first = self._live_first_t
        self._live_first_t = data.timestamp_s if first is None else first
        self.log.sequence_s = data.timestamp_s - self._live_first_t
        return out

    def end(self, ended_by: BaseException | None = None) -> RunLog:
        """End the run ``begin`` started (ended_by: the exception that ended it, None when the caller has no more
        frames): let local mapping and loop closing finish their queues (stop them at once after a failure), then
        fire ``slamkit_run_finished``. Raises PipelineThreadError when a pipeline thread failed."""
        workers, self._live_workers = self._live_workers, []
        try:
            self._live_stack.close()
            finished = False
            try:
                if ended_by is None and self._fault is None:
                    self._drain(workers)
                    finished = True
            finally:
                if not finished or self._fault is not None:
                    self._stop_all(workers)
                self.log.wall_s = time.perf_counter() - self._live_start
            if self._fault is not None and ended_by is None:
                ended_by = self._fault.as_error()
                raise ended_by
        except BaseException as exc:
            ended_by = ended_by or exc
            raise
        finally:
            thaw_startup_heap()  # begin's warm-up froze the start-up heap for the run's duration only
            self._run_events.finished(self.log, ended_by)
        return self.log

    def _track_frames(self, camera: Camera, bar: tqdm[Any], on_frame: Callable[[TrackingOutcome], None] | None) -> None:
        """The tracking loop: take frames from the source until the end, a fault or a stop."""
        assert self._source is not None
        while self._fault is None or self._fault.thread_name == self._source.name:
            item = self._source.get()
            if item is None or item is END:
                break
            assert isinstance(item, FrameData)
            try:
                t_track = time.perf_counter()
                out = self._track(item, camera)
                self.log.tracking_wall_s.append((t_track, time.perf_counter()))
            except Exception as exc:  # reported like any other thread's failure
                if raised_by_ctrl_c(exc):
                    raise KeyboardInterrupt from exc
                self._on_fault(ThreadFault("tracking", exc, traceback.format_exc()))
                break
            if on_frame is not None:
                on_frame(out)
            bar.update(1)
            bar.set_postfix_str(
                f"{out.state.value} kf={self.store.n_keyframes()} mp={self.store.n_points()} "
                f"q={self._mapping.pending() if self._mapping is not None else 0} drop={self._source.frames_dropped}",
                refresh=False,
            )

    def _prepare(self, dataset: Dataset, camera: Camera) -> None:
        """One-off work before the clock starts: the dataset's own preparation (the synthetic world's textures)
        and a throw-away feature extraction that loads the compiled kernels."""
        t0 = time.perf_counter()
        prepare = getattr(dataset, "prepare_playback", None)
        if callable(prepare):
            prepare()
        self.tracker.warm_up(camera)
        log.info("prepared playback in %.2f s", time.perf_counter() - t0)

    def _frame_skipped(self, frame_index: int, reason: str) -> None:
        """A frame the dataset could not read (called from the frame source's thread)."""
        self.log.frames_skipped += 1
        self._run_events.frame_skipped(frame_index, reason)

    def _preloaded(self, dataset: Iterable[FrameData], n_frames: int) -> list[FrameData]:
        """Every frame of the dataset, read (rendered) now; records their memory in ``log.preloaded_mb``."""
        frames: list[FrameData] = []
        nbytes = 0
        for data in tqdm(dataset, total=n_frames, unit="frame", desc="preloading", disable=not self.progress):
            frames.append(data)
            images = (data.image, data.color, data.depth_m, data.image_right)
            nbytes += sum(a.nbytes for a in images if a is not None)
        self.log.preloaded_mb = nbytes / 2**20
        log.info("preloaded %d frames (%.0f MiB) before playback", len(frames), self.log.preloaded_mb)
        return frames

    def _lower_optimizer_process_priority(self) -> None:
        """A worker process serving only local mapping and loop closing (GTSAM offloaded) is background work too."""
        if self.mapper is None:
            return
        optimizer = self.mapper.optimizer
        pid = getattr(optimizer, "pid", None)
        if self.realtime and isinstance(pid, int) and optimizer is not self.tracker.optimizer:
            lower_process_priority(pid, self.background_niceness)

    def _drain(self, workers: list[PipelineWorker[KeyFrame]]) -> None:
        """End of the sequence: let local mapping, then loop closing, finish their queues."""
        for worker in workers:  # mapping first: it feeds loop closing
            worker.stop(drain=True)
            worker.join(timeout=DRAIN_TIMEOUT_S)
            if worker.is_alive():
                fault = ThreadFault(
                    worker.name,
                    TimeoutError(f"did not finish its queue within {DRAIN_TIMEOUT_S:.0f} s"),
                    "",
                )
                self._on_fault(fault)
                return
        if self.loop_closer is not None:
            # ORB-SLAM2 Shutdown waits for a running global BA
            self.loop_closer.join_global_ba()
            if self.loop_closer.global_ba_error is not None:
                self._on_fault(ThreadFault("global-ba", self.loop_closer.global_ba_error, ""))

    def _stop_all(self, workers: list[PipelineWorker[KeyFrame]]) -> None:
        if self.loop_closer is not None:
            self.loop_closer.abort_global_ba()
        for worker in workers:
            worker.stop(drain=False)
        for worker in workers:
            worker.join(timeout=STOP_TIMEOUT_S)
            if worker.is_alive():
                log.error("the %s thread did not stop within %.0f s; leaving it", worker.name, STOP_TIMEOUT_S)


__all__ = ["PipelineThreadError", "ThreadedRunner"]
