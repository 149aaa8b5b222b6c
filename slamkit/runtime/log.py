"""RunLog: what a run did, frame by frame and keyframe by keyframe (shared by every runner)."""

from __future__ import annotations

from dataclasses import dataclass, field

from slamkit.map.atlas import Atlas, MapChange
from slamkit.pipeline.outcomes import LoopOutcome, MappingOutcome, TrackingOutcome
from slamkit.pipeline.trajectory import KeptFrames, TrajectoryRecorder
from slamkit.sensors import FrameRecords


@dataclass
class RunLog:
    """Everything a run did.

    tracking: one outcome per frame tracking received (in order). mapping / loops: one outcome per keyframe local
    mapping / loop closing processed. resets: active maps erased because tracking was lost soon after initialising
    them; new_maps: maps kept in the Atlas when tracking was lost for good (a new active map started); maps_merged:
    merges of two maps of the Atlas (ORB-SLAM3 map merging: one per ``slamkit_maps_merged`` event the runner fires).
    frames_dropped: frames that real-time playback delivered while tracking was busy and that were replaced by a
    newer one before tracking took them, and frames the camera's buffer replaced while the frame source was busy
    extracting features ahead (``runner.realtime_camera_buffer``; 0 when playing as fast as possible);
    dropped_frames: those frames, (frame index, timestamp s) each. source_end: how a live source's stream ended
    (None for a recorded sequence).
    sequence_s: time span of the frames played (last minus first timestamp, s). wall_s: wall time of the run, s. failed_thread: name of the pipeline thread whose exception stopped the run, if any.
    preloaded_mb: memory held by frames read into memory before playback (``runner.preload``), MiB.
    """

    tracking: list[TrackingOutcome] = field(default_factory=list)
    mapping: list[MappingOutcome] = field(default_factory=list)
    loops: list[LoopOutcome] = field(default_factory=list)
    resets: int = 0
    new_maps: int = 0
    maps_merged: int = 0
    wall_s: float = 0.0
    frames_dropped: int = 0
    dropped_frames: list[tuple[int, float]] = field(default_factory=list)
    source_end: str | None = None
    frames_skipped: int = 0  # frames the dataset could not read, left out (runner.bad_frames: skip)
    sequence_s: float = 0.0
    runner: str = "sequential"
    failed_thread: str | None = None
    preloaded_mb: float = 0.0
    # wall-clock intervals (time.perf_counter(), s) of each frame's tracking and of each local BA, recorded by
    # the threaded runner: how fast does tracking run while a local BA runs beside it?
    tracking_wall_s: list[tuple[float, float]] = field(default_factory=list)
    local_ba_wall_s: list[tuple[float, float]] = field(default_factory=list)

    @property
    def realtime_factor(self) -> float | None:
        """Sequence time over wall time: 1.0 keeps pace with the camera, above 1 runs faster than it."""
        if self.wall_s <= 0.0 or self.sequence_s <= 0.0:
            return None
        return self.sequence_s / self.wall_s


def log_tracking_outcome(
    log: RunLog,
    recorder: TrajectoryRecorder,
    out: TrackingOutcome,
    map_change: MapChange | None,
    kept: KeptFrames | None = None,
    map_before: int | None = None,
) -> None:
    """What every runner does after tracking a frame: count a map reset or a new map, log the outcome, and record
    the initialisation's reference frame, which became keyframe 0 and has an estimated pose too. The runner's
    recorder holds the active map's frames: it starts again when the active map changes (the run directory keeps
    every map's frames: the outputs plugin records them per map from the lifecycle events; ``kept``, the runner's
    frames of the other maps for its map file, takes those of the map ``map_before`` left for a new one)."""
    if map_change is not None:
        if kept is not None and map_before is not None:
            kept.map_changed(map_change, map_before, recorder)
        recorder.clear()
    if map_change == MapChange.RESET:
        log.resets += 1
    elif map_change == MapChange.NEW_MAP:
        log.new_maps += 1
    log.tracking.append(out)
    # a stereo/RGB-D map starts from the tracked frame itself (one keyframe): no other frame to record
    if out.initialized_map and out.new_keyframes and out.new_keyframes[0].frame_index != out.frame_index:
        kf_ini = out.new_keyframes[0]
        recorder.record(kf_ini.frame_index, kf_ini.timestamp_s, kf_ini.T_c_w, kf_ini.id, kf_ini.T_c_w)


def map_frames(atlas: Atlas, recorder: TrajectoryRecorder, kept: KeptFrames) -> dict[int, FrameRecords]:
    """map id -> every frame of that map a runner knows (this run's and, from a loaded map file, the earlier
    sessions'), each relative to a keyframe the map has now: what ``map.save`` writes with the Atlas
    (slamkit/map/mapfile.py). The keyframe ids are read under each map's read lock."""
    kf_ids: dict[int, list[int]] = {}
    for map_id, store in atlas.items():
        with store.read():
            kf_ids[map_id] = list(store.keyframe_ids())
    return kept.export(kf_ids, atlas.active_id, recorder)
