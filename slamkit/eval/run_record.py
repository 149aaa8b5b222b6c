"""A run's account rebuilt from its lifecycle events (slamkit/events.py): what the outputs plugin writes.

It keeps the same records a runner keeps in its ``RunLog`` (one per frame, per keyframe mapped, per keyframe loop
closing processed) and the trajectory the way ORB-SLAM records it (each frame relative to its reference keyframe,
resolved against the keyframes' final poses at the end), so :func:`slamkit.eval.run_metrics.run_metrics` gives the
same numbers from either.
"""

from __future__ import annotations

from slamkit.events import (
    FrameTracked,
    KeyFrameCulled,
    KeyFrameInserted,
    LoopChecked,
    MapCreated,
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
        self.mapping: list[KeyFrameInserted] = []
        self.loops: list[LoopChecked] = []
        self.finished: RunFinished | None = None
        self._trajectory = TrajectoryRecorder()

    # ---- events ----------------------------------------------------------------------------------

    def on_map_created(self, event: MapCreated) -> None:
        # the initialisation's reference frame became keyframe 0: it has an estimated pose too
        first = event.keyframes[0]
        self._trajectory.record(first.frame_index, first.timestamp_s, first.T_c_w, first.kf_id, first.T_c_w)

    def on_frame_tracked(self, event: FrameTracked) -> None:
        if event.map_reset:
            self._trajectory.clear()  # the poses so far live in a map that no longer exists
        self.tracking.append(event)
        if event.T_c_r is not None and event.reference_kf_id is not None:
            self._trajectory.record_relative(event.frame_index, event.timestamp_s, event.reference_kf_id, event.T_c_r)

    def on_keyframe_inserted(self, event: KeyFrameInserted) -> None:
        self.mapping.append(event)

    def on_keyframe_culled(self, event: KeyFrameCulled) -> None:
        self._trajectory.on_culled(CulledKeyFrame(event.kf_id, event.parent_id, event.T_kf_parent, event.T_c_w))

    def on_loop_checked(self, event: LoopChecked) -> None:
        self.loops.append(event)

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
    def wall_s(self) -> float:
        return self._finished().wall_s

    @property
    def frames_dropped(self) -> int:
        return self._finished().frames_dropped

    @property
    def realtime_factor(self) -> float | None:
        return self._finished().realtime_factor

    @property
    def preloaded_mb(self) -> float:
        return self._finished().preloaded_mb

    @property
    def final_map(self) -> MapSnapshot:
        """The active map at the end of the run."""
        return self._finished().maps[-1]

    # ---- trajectories ----------------------------------------------------------------------------

    def frames(self) -> Trajectory:
        """Every recorded frame's pose T_w_c, against the keyframes' final poses."""
        return self._trajectory.frames_at(self.final_map.keyframe_poses())

    def keyframes(self) -> Trajectory:
        """The final map's keyframes, T_w_c in time order."""
        snap = self.final_map
        order = sorted(range(snap.n_keyframes), key=lambda i: snap.keyframe_timestamps_s[i])
        if not order:
            return Trajectory(snap.keyframe_timestamps_s[:0], snap.T_w_c[:0])
        return Trajectory(snap.keyframe_timestamps_s[order], snap.T_w_c[order])
