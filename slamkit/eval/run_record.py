"""A run's account rebuilt from its lifecycle events (slamkit/events.py): what the outputs plugin writes.

It keeps the same records a runner keeps in its ``RunLog`` (one per frame, per keyframe mapped, per keyframe loop
closing processed) and the trajectory the way ORB-SLAM records it (each frame relative to its reference keyframe,
resolved against the keyframes' final poses at the end), so :func:`slamkit.eval.run_metrics.run_metrics` gives the
same numbers from either. Frames are recorded per map of the Atlas (``FrameTracked.map_id``): each map has its own
trajectory, and the run's main trajectory is that of the map with the most keyframes (ORB-SLAM3
System::SaveTrajectoryEuRoC writes the biggest map's). A run on a loaded map file starts each map's trajectory from
the frames the file kept for it (earlier sessions: ``RunStarted.loaded_frames``), so a map's trajectory holds every
session's frames, placed against the keyframes as this run leaves them.
"""

from __future__ import annotations

import numpy as np

from slamkit.events import (
    FrameSkipped,
    FrameTracked,
    KeyFrameCulled,
    KeyFrameInserted,
    LoopChecked,
    MapCreated,
    MapsMerged,
    MapSnapshot,
    RunFinished,
    RunStarted,
)
from slamkit.pipeline.outcomes import CulledKeyFrame
from slamkit.pipeline.trajectory import TrajectoryRecorder
from slamkit.sensors import Trajectory


class RunRecord:
    """Everything one run's events said, in the order they came (see :class:`slamkit.eval.run_metrics.RunAccount`).

    Feed it the events of one run (``on_*``); after :meth:`on_run_finished` it has the run's totals
    (``finished``), its final map and its trajectories (:meth:`frames`, :meth:`keyframes`).
    """

    def __init__(self, started: RunStarted) -> None:
        self.started = started
        self.tracking: list[FrameTracked] = []
        self.skipped: list[FrameSkipped] = []  # frames the dataset could not read, left out of the run
        self.mapping: list[KeyFrameInserted] = []
        self.loops: list[LoopChecked] = []
        self.merges: list[MapsMerged] = []
        self.finished: RunFinished | None = None
        self._trajectories: dict[int, TrajectoryRecorder] = {}  # map id -> that map's frames
        for map_id, records in started.loaded_frames.items():  # earlier sessions' frames (map.load): theirs too
            self._trajectory(map_id).load(records)

    def _trajectory(self, map_id: int) -> TrajectoryRecorder:
        recorder = self._trajectories.get(map_id)
        if recorder is None:
            recorder = self._trajectories[map_id] = TrajectoryRecorder()
        return recorder

    # ---- events ----------------------------------------------------------------------------------

    def on_map_created(self, event: MapCreated) -> None:
        # the initialisation's reference frame became keyframe 0: it has an estimated pose too (a stereo/RGB-D map
        # starts from one keyframe, the tracked frame itself, which on_frame_tracked records)
        if len(event.keyframes) < 2:
            return
        first = event.keyframes[0]
        self._trajectory(event.map_id).record(
            first.frame_index, first.timestamp_s, first.T_c_w, first.kf_id, first.T_c_w
        )

    def on_frame_skipped(self, event: FrameSkipped) -> None:
        self.skipped.append(event)

    def on_frame_tracked(self, event: FrameTracked) -> None:
        # after a map reset the poses recorded so far live under the erased map's id, which no map has any more
        self.tracking.append(event)
        if event.T_c_r is not None and event.reference_kf_id is not None:
            self._trajectory(event.map_id).record_relative(
                event.frame_index, event.timestamp_s, event.reference_kf_id, event.T_c_r
            )

    def on_keyframe_inserted(self, event: KeyFrameInserted) -> None:
        self.mapping.append(event)

    def on_keyframe_culled(self, event: KeyFrameCulled) -> None:
        self._trajectory(event.map_id).on_culled(
            CulledKeyFrame(event.kf_id, event.parent_id, event.T_kf_parent, event.T_c_w)
        )

    def on_loop_checked(self, event: LoopChecked) -> None:
        self.loops.append(event)

    def on_maps_merged(self, event: MapsMerged) -> None:
        """The active map (``into_map_id``) absorbed another: its frames, recorded so far in its previous scale, are
        rescaled (the move's scale is the cube root of its rotation block's determinant), then the absorbed map's
        frames join it (their keyframes now belong to it)."""
        self.merges.append(event)
        scale = float(np.cbrt(np.linalg.det(np.asarray(event.T_into_merged)[:3, :3])))
        into = self._trajectory(event.into_map_id)
        into.rescale(None, scale)
        absorbed = self._trajectories.pop(event.merged_map_id, None)
        if absorbed is not None:
            into.absorb(absorbed)

    def on_run_finished(self, event: RunFinished) -> None:
        self.finished = event

    # ---- the run's totals (RunAccount) -------------------------------------------------------------

    def _finished(self) -> RunFinished:
        if self.finished is None:
            raise RuntimeError("the run has not finished: no slamkit_run_finished event yet")
        return self.finished

    @property
    def runner(self) -> str:
        return self.started.runner

    @property
    def resets(self) -> int:
        return self._finished().resets

    @property
    def maps_merged(self) -> int:
        """Merges of two maps of the Atlas the run's events reported (``slamkit_maps_merged``)."""
        return len(self.merges)

    @property
    def wall_s(self) -> float:
        return self._finished().wall_s

    @property
    def frames_skipped(self) -> int:
        return len(self.skipped)

    @property
    def frames_dropped(self) -> int:
        return self._finished().frames_dropped

    @property
    def realtime_factor(self) -> float | None:
        return self._finished().realtime_factor

    @property
    def source_end(self) -> str | None:
        return self._finished().source_end

    @property
    def preloaded_mb(self) -> float:
        return self._finished().preloaded_mb

    @property
    def maps(self) -> tuple[MapSnapshot, ...]:
        """Every map of the Atlas at the end of the run, ascending ids."""
        return self._finished().maps

    @property
    def main_map(self) -> MapSnapshot:
        """The map with the most keyframes (ties: the lowest id), whose trajectory is the run's (ORB-SLAM3
        SaveTrajectoryEuRoC / SaveKeyFrameTrajectoryEuRoC keep the biggest map)."""
        return max(self.maps, key=lambda m: (m.n_keyframes, -m.map_id))

    # ---- trajectories ----------------------------------------------------------------------------

    def frames(self, snapshot: MapSnapshot | None = None, loaded: bool = True) -> Trajectory:
        """Every frame recorded in a map (default: the main map), T_w_c against its keyframes' final poses; loaded:
        with the frames of earlier sessions a loaded map file kept for it (False: this run's frames only)."""
        snap = self.main_map if snapshot is None else snapshot
        return self._trajectory(snap.map_id).frames_at(snap.keyframe_poses(), loaded)

    def keyframes(self, snapshot: MapSnapshot | None = None) -> Trajectory:
        """A map's keyframes (default: the main map's), T_w_c in time order."""
        snap = self.main_map if snapshot is None else snapshot
        order = sorted(range(snap.n_keyframes), key=lambda i: snap.keyframe_timestamps_s[i])
        if not order:
            return Trajectory(snap.keyframe_timestamps_s[:0], snap.T_w_c[:0])
        return Trajectory(snap.keyframe_timestamps_s[order], snap.T_w_c[order])
