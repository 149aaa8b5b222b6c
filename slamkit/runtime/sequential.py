"""The deterministic runner: tracking, then local mapping of each new keyframe, in one thread and in a fixed
order. With a fixed seed, two runs give the same trajectory bit for bit. Lifecycle hooks are called inline, from
this thread, right after the step that produced each event (slamkit/runtime/events.py)."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from tqdm import tqdm

from slamkit.errors import ConfigError
from slamkit.geometry.sim3 import Sim3
from slamkit.interfaces import Camera, Dataset, MapStore
from slamkit.map.atlas import Atlas, MapChange
from slamkit.pipeline.local_mapping import LocalMapper
from slamkit.pipeline.loop_closing import LoopCloser, MapMerge
from slamkit.pipeline.loop_correction import pose_of_sim3, sim3_of_pose
from slamkit.pipeline.lost import LostDecision
from slamkit.pipeline.outcomes import MappingState, TrackingOutcome, TrackingState
from slamkit.pipeline.tracking import Tracker
from slamkit.pipeline.trajectory import KeptFrames, TrajectoryRecorder
from slamkit.runtime.events import EventDispatcher, RunEvents
from slamkit.runtime.log import RunLog, log_tracking_outcome, map_frames
from slamkit.runtime.modelled_mapping import modelled_mapping
from slamkit.runtime.source import check_bad_frames_policy, frame_count, is_live, readable_frames
from slamkit.runtime.workers import raised_by_ctrl_c
from slamkit.sensors import FrameData, FrameRecords

log = logging.getLogger("slamkit.runner")

RECORD_REFERENCES = ("tracked", "mapped")  # runner.record_reference (SequentialRunner)


class SequentialRunner:
    """Runs a dataset through tracking and local mapping, one frame at a time."""

    def __init__(
        self,
        tracker: Tracker,
        mapper: LocalMapper | None,
        atlas: Atlas,
        progress: bool = True,
        loop_closer: LoopCloser | None = None,
        events: EventDispatcher | None = None,
        bad_frames: str = "skip",
        record_reference: str = "tracked",
        modelled_mapping_ms: float = 0.0,
        modelled_mapping_new_map_ms: float | None = None,
    ) -> None:
        """mapper: local mapping (None: localization only, ``mode=localization``: tracking makes no keyframe).
        events: fires the plugins' lifecycle hooks (None: nobody listens). bad_frames: what to do with a frame
        the dataset cannot read, "skip" (logged and reported) or "stop" (slamkit.runtime.source.readable_frames).
        record_reference: the reference keyframe pose a frame's pose is recorded against (its T_c_r), "tracked"
        (the pose tracking read, ORB-SLAM2/3 Tracking::Track's mlRelativeFramePoses and the threaded runner) or
        "mapped" (the keyframe as it is after the frame's keyframes were mapped: a keyframe's own frame then carries
        the inverse of its first local BA's correction). modelled_mapping_ms: local mapping's modelled time per
        keyframe, ms of sequence time, during which monocular tracking sees local mapping busy and makes no keyframe
        (:class:`ModelledMapping`; 0: always idle); modelled_mapping_new_map_ms: the same for each of the keyframes a
        new map is created with (None: modelled_mapping_ms). Stereo/RGB-D frames always see it idle."""
        self.tracker = tracker
        self.mapper = mapper
        self.loop_closer = loop_closer
        self.atlas = atlas
        self.recorder = TrajectoryRecorder()
        #: the frames of the Atlas's maps the recorder does not hold (earlier sessions', other maps'): map_frames()
        self.kept_frames = KeptFrames(getattr(atlas, "loaded_frames", None) or {})
        self.progress = progress
        self.bad_frames = check_bad_frames_policy(bad_frames)
        if record_reference not in RECORD_REFERENCES:
            raise ConfigError(
                f"runner.record_reference = {record_reference!r}: expected one of {', '.join(RECORD_REFERENCES)}"
            )
        self.record_reference = record_reference
        self.modelled_mapping = modelled_mapping(modelled_mapping_ms, modelled_mapping_new_map_ms)
        self._depth_frames = False  # the frames tracked so far carry depth (stereo/RGB-D: the model does not apply)
        self.log = RunLog()
        self.events = events
        self._run_events = RunEvents(None, "sequential", atlas)
        self._first_t: float | None = None  # timestamp of the run's first frame, s
        self._start = time.perf_counter()  # wall clock at the run's start (perf_counter), s
        self._merge_G: Sim3 | None = None  # the last merge's move of the active map (x_new = G x_old)
        if loop_closer is not None:
            loop_closer.on_merge = self._on_merge

    def _on_merge(self, merge: MapMerge) -> None:
        """Loop closing moves the active map into another map's frame to merge them: the frames recorded relative to
        the moved keyframes follow the move's scale; slamkit_maps_merged fires."""
        self.recorder.rescale(merge.moved_kf_ids, merge.G.s)
        self.kept_frames.merged(merge.into_map_id, merge.merged_map_id, merge.moved_kf_ids, merge.G.s)
        self.tracker.map_moved(merge.G)  # the motion model's velocity follows the move's scale
        self._merge_G = merge.G
        self.log.maps_merged += 1
        self._run_events.maps_merged(
            merge.kf_id, merge.matched_kf_id, merge.merged_map_id, merge.into_map_id, merge.G.matrix()
        )

    def map_frames(self) -> dict[int, FrameRecords]:
        """map id -> every frame of that map, this run's and the earlier sessions' a loaded map file kept, each
        relative to a keyframe the map has now (slamkit.runtime.log.map_frames): what ``map.save`` writes."""
        return map_frames(self.atlas, self.recorder, self.kept_frames)

    @property
    def store(self) -> MapStore:
        """The active map of the Atlas."""
        return self.atlas.active

    def run(
        self,
        dataset: Dataset,
        camera: Camera,
        on_frame: Callable[[TrackingOutcome], None] | None = None,
        run_dir: Path | None = None,
        config: Mapping[str, Any] | None = None,
    ) -> RunLog:
        """Process every frame; results accumulate in ``self.log`` and ``self.recorder`` even if it raises.

        run_dir / config: where the run's files go and its resolved config, handed to the lifecycle hooks
        (``slamkit_run_started``; the built-in outputs plugin writes the run directory from its events).
        The same as ``begin``, ``step`` on each readable frame, then ``end`` (what slamkit.api.System does with
        frames a program hands it). A live source (``dataset=camera``) is a ConfigError: reading it one frame at a
        time between the pipeline's steps would track ever staler frames (the threaded runner plays it).
        """
        if is_live(dataset):
            raise ConfigError(
                f"runner=sequential cannot run the live source {getattr(dataset, 'name', '?')}: a camera runs in real "
                "time with runner=threaded (the default)"
            )
        self.begin(dataset, camera, run_dir, config)
        bar = tqdm(total=frame_count(dataset), unit="frame", disable=not self.progress, dynamic_ncols=True)
        ended_by: BaseException | None = None
        try:
            for data in readable_frames(dataset, self.bad_frames, self._frame_skipped):
                out = self.step(data, camera)
                if on_frame is not None:
                    on_frame(out)
                bar.update(1)
                bar.set_postfix_str(
                    f"{out.state.value} kf={self.store.n_keyframes()} mp={self.store.n_points()}", refresh=False
                )
        except BaseException as exc:
            if isinstance(exc, Exception) and raised_by_ctrl_c(exc):
                # Ctrl-C inside a callback from compiled code: an interrupt all the same
                ended_by = KeyboardInterrupt()
                raise ended_by from exc
            ended_by = exc
            raise
        finally:
            bar.close()
            self.end(ended_by)
        return self.log

    def begin(
        self, dataset: Dataset, camera: Camera, run_dir: Path | None = None, config: Mapping[str, Any] | None = None
    ) -> None:
        """Start a run: fire ``slamkit_run_started`` (dataset: its name, length and ground truth for the
        listeners; run_dir / config as in ``run``) and start the wall clock. Then ``step`` each frame, then
        ``end``. camera: the frames' camera (unused here; the threaded runner's ``begin`` warms up the front end
        with it)."""
        del camera
        self._run_events = RunEvents(self.events, "sequential", self.atlas)
        self._run_events.started(dataset, run_dir, config, threaded=False)
        self._first_t = None
        self._start = time.perf_counter()
        self.modelled_mapping.reset()

    def end(self, ended_by: BaseException | None = None) -> RunLog:
        """End the run ``begin`` started (ended_by: the exception that ended it, None when it completed): record
        its wall time and fire ``slamkit_run_finished`` (the outputs plugin writes the run directory)."""
        self.log.wall_s = time.perf_counter() - self._start
        self._run_events.finished(self.log, ended_by)
        return self.log

    def _frame_skipped(self, frame_index: int, reason: str) -> None:
        self.log.frames_skipped += 1
        self._run_events.frame_skipped(frame_index, reason)

    def step(self, data: FrameData, camera: Camera) -> TrackingOutcome:
        """Track one frame, then map the keyframes it produced (and look for a loop at each), then record its pose;
        returns what tracking did with it (also appended to ``self.log.tracking``). The one per-frame step of
        ``run`` and of slamkit.api.System.track.

        Local mapping runs to completion in between frames, so it is idle when a frame is tracked and every
        keyframe tracking wants is made — unless ``runner.modelled_mapping_ms`` > 0: then a monocular frame
        captured within that time of a keyframe sees local mapping busy (:class:`ModelledMapping`) and tracking
        makes no keyframe from it (ORB-SLAM's monocular NeedNewKeyFrame). A map reset or a new map tracking asks for
        is carried out right after the frame."""
        self._first_t = data.timestamp_s if self._first_t is None else self._first_t
        self.log.sequence_s = data.timestamp_s - self._first_t
        map_before = self.atlas.active_id
        mapping = MappingState(idle=True, accepting_keyframes=True)
        if not self._depth_frames:
            mapping = self.modelled_mapping.state(data.timestamp_s)
        out = self.tracker.step(data, camera, mapping)
        frame = self.tracker.current_frame
        if frame is not None and frame.index == out.frame_index:
            self._depth_frames = frame.features.bf > 0.0
        self.modelled_mapping.keyframes_made(data.timestamp_s, len(out.new_keyframes), out.initialized_map)
        if out.lost_decision == LostDecision.RESET_MAP:
            self.tracker.reset()
            self.modelled_mapping.reset()
        elif out.lost_decision == LostDecision.NEW_MAP:
            self.tracker.start_new_map()
            self.modelled_mapping.reset()
        map_change = self.atlas.change_since(map_before)  # reset, or a new map with the old one kept
        map_was_reset = map_change == MapChange.RESET
        log_tracking_outcome(self.log, self.recorder, out, map_change, self.kept_frames, map_before)
        self._run_events.map_events(out)
        merges_before = self.log.maps_merged
        for kf in out.new_keyframes:
            if self.mapper is None:
                raise RuntimeError(f"frame {out.frame_index}: a keyframe was made in a run without local mapping")
            mapped = self.mapper.step(kf)
            self.log.mapping.append(mapped)
            for culled in mapped.culled_keyframes:
                self.recorder.on_culled(culled)
                self.kept_frames.on_culled(self.atlas.active_id, culled)
            self._run_events.keyframe_mapped(mapped)
            if self.loop_closer is not None and self.store.has_keyframe(kf.id):
                self.log.loops.append(self.loop_closer.step(kf))
                self._run_events.loop_checked(self.log.loops[-1])
        if self.log.maps_merged != merges_before and out.T_c_w is not None and self._merge_G is not None:
            # a merge moved the map after this frame was tracked: its pose moves with the map (recorded below
            # against its reference keyframe as it is now)
            out.T_c_w = pose_of_sim3(sim3_of_pose(out.T_c_w) @ self._merge_G.inverse())
        ref, T_ref_w = None, None
        merged = self.log.maps_merged != merges_before
        if out.state == TrackingState.OK and out.T_c_w is not None:
            ref = out.reference_kf_id
            if ref is not None and self.store.has_keyframe(ref):
                if self.record_reference == "tracked" and out.T_ref_w is not None and not merged:
                    # ORB-SLAM2/3 (Tracking::Track): Tcr = mTcw * mpReferenceKF->GetPoseInverse() right after tracking,
                    # before local mapping moves the keyframe (as the threaded runner records)
                    T_ref_w = out.T_ref_w
                else:
                    # the reference keyframe as it is after its mapping (and a loop correction or a merge's move,
                    # which out.T_c_w followed above)
                    T_ref_w = self.store.get_keyframe(ref).T_c_w
                self.recorder.record(out.frame_index, out.timestamp_s, out.T_c_w, ref, T_ref_w)
        # after the frame's keyframes were mapped: its pose is recorded against its reference keyframe as it is now
        self._run_events.frame_tracked(out, map_was_reset, ref, T_ref_w, data.image, self.tracker.current_frame)
        out.release_keyframes()  # the map holds those it kept; the log must not keep the culled ones alive
        return out
