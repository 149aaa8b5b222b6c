"""The lifecycle events of a run: what the ``slamkit_*`` lifecycle hooks (slamkit/hookspecs.py) receive.

Every event is a frozen dataclass of plain data: ids, timestamps (s), poses as float64 (4, 4) arrays named by
convention (``T_c_w`` maps world points into the camera, ``T_w_c`` its inverse), counts, timings (ms) and the id
of the map it happened in. No event holds the map store, an entity or a pipeline object, so a listener can keep
an event as long as it likes, hand it to another thread or process, and never changes the run by reading it.
Arrays in an event are the listener's to read, not to write.

``run_id`` identifies the run an event belongs to (unique within the process): a plugin that keeps state per run
keys it on ``run_id`` and drops it at :class:`RunFinished`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slamkit.interfaces import MapStore
from slamkit.sensors import FrameRecords, Trajectory

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]
I64 = NDArray[np.int64]
Bool = NDArray[np.bool_]


@dataclass(frozen=True)
class RunStarted:
    """A run begins (before the first frame is read).

    runner: "sequential" or "threaded". dataset: the dataset's name ("synthetic/room"). n_frames: frames the
    dataset will deliver (None: unknown, a live source such as ``dataset=camera``). run_dir: the run's output directory (None: the caller wants no files, e.g. a test or a
    notebook driving the runner). config: the run's composed config, resolved, as plain containers (empty when
    the caller gave none). ground_truth: the dataset's ground-truth trajectory (T_w_c per timestamp), if any.
    K: (3, 3) the (left) camera's pinhole intrinsics, px, and image_size (width, height) px — None when unknown.
    loaded_frames: map id -> the frames of earlier sessions a loaded map file kept for that map (``map.load``;
    docs/atlas.md, "Multi-session"), each relative to a keyframe of the map: a recorder of the run's trajectory
    starts from them, so it holds every session's frames against the keyframes as this run leaves them.
    """

    run_id: int
    runner: str
    dataset: str
    n_frames: int | None
    run_dir: Path | None = None
    config: Mapping[str, Any] = field(default_factory=dict)
    ground_truth: Trajectory | None = None
    K: F64 | None = None
    image_size: tuple[int, int] | None = None
    loaded_frames: Mapping[int, FrameRecords] = field(default_factory=dict)


@dataclass(frozen=True)
class FrameTracked:
    """Tracking finished one frame (every frame tracking received, tracked or not).

    state: "not_initialized", "ok" or "lost" (TrackingState values). method: how the pose was found
    ("initialize", "motion_model", "reference_keyframe", "relocalization", ...). T_c_w: (4, 4) the estimated
    pose (None when not tracked). reference_kf_id / T_c_r: the frame's reference keyframe and the frame's pose
    relative to it, (4, 4) = T_c_w @ T_w_r (ORB-SLAM records the trajectory this way so later corrections of the
    keyframe move the frame too); None when the frame has no pose to record. map_reset: tracking reset the map
    at this frame (the trajectory so far lived in a map that no longer exists). timings_ms: per stage (``track_ms``
    the whole frame, ``extract_ms``, ...).

    For a viewer (None when the runner has none to give): image, the frame's (left) image as read, (H, W) or
    (H, W, 3) uint8, not copied; uv_px, its keypoints in that image, (N, 2) float32 px; tracked, (N,) bool, the
    keypoints matched to a map point.
    """

    run_id: int
    map_id: int
    frame_index: int
    timestamp_s: float
    state: str
    method: str
    n_features: int
    inliers: int
    T_c_w: F64 | None
    reference_kf_id: int | None
    T_c_r: F64 | None
    map_reset: bool
    timings_ms: Mapping[str, float]
    message: str = ""
    image: NDArray[np.uint8] | None = None
    uv_px: F32 | None = None
    tracked: Bool | None = None


@dataclass(frozen=True)
class FrameSkipped:
    """A frame the dataset could not read (a missing, undecodable or truncated image) was left out of the run
    (``runner.bad_frames: skip``). frame_index: the frame's number in the sequence (the frames after it keep
    theirs). reason: the reading error, naming the file."""

    run_id: int
    frame_index: int
    reason: str


@dataclass(frozen=True)
class InitialKeyFrame:
    """One of the keyframes an initialisation made: id, the frame it came from, its time and pose (4, 4)."""

    kf_id: int
    frame_index: int
    timestamp_s: float
    T_c_w: F64


@dataclass(frozen=True)
class MapCreated:
    """A map was created: tracking initialised it (the first map of the run, the active map again after a reset, or
    a new map of the Atlas after tracking was lost for good; ``map_id`` is its Atlas id, slamkit/map/atlas.py).

    keyframes: the initialisation's keyframes (monocular: the reference frame's first, then the current frame's),
    with their poses at initialisation. n_points: map points triangulated by the initialisation. Fired before the
    :class:`FrameTracked` of the frame that initialised the map.
    """

    run_id: int
    map_id: int
    frame_index: int
    timestamp_s: float
    keyframes: tuple[InitialKeyFrame, ...]
    n_points: int


@dataclass(frozen=True)
class KeyFrameInserted:
    """Local mapping inserted a keyframe into the map and finished its work on it (ORB-SLAM VI-A..E).

    points_created: new points triangulated with its neighbours; points_fused: duplicates merged;
    ba_outliers: observations the local BA rejected; ba_aborted: the local BA was stopped early by a newer
    keyframe; ba_due: the keyframe was due a local BA; ba_skipped: it was due, but a newer keyframe's abort came
    before it started. timings_ms: per stage of local mapping (``local_ba_ms``, ...). T_c_w: (4, 4) its pose after local
    mapping; point_ids (M,) / points_w (M, 3) m: the map points it observes then, in the world frame (None when the
    keyframe was gone by then).
    """

    run_id: int
    map_id: int
    kf_id: int
    points_created: int
    points_fused: int
    ba_outliers: int
    ba_aborted: bool
    timings_ms: Mapping[str, float]
    T_c_w: F64 | None = None
    point_ids: I64 | None = None
    points_w: F64 | None = None
    ba_due: bool = False
    ba_skipped: bool = False


@dataclass(frozen=True)
class PointsCulled:
    """Local mapping's recent-point culling (ORB-SLAM VI-B) removed ``n_points`` map points while processing
    keyframe ``kf_id``. Fired only when it removed at least one."""

    run_id: int
    map_id: int
    kf_id: int
    n_points: int


@dataclass(frozen=True)
class KeyFrameCulled:
    """Local mapping's keyframe culling (ORB-SLAM VI-E) removed keyframe ``kf_id``.

    parent_id: its spanning-tree parent when it was removed (None if it had none). T_kf_parent: (4, 4) its pose
    relative to that parent, so a frame that referred to it can still be placed after the parent moves.
    T_c_w: (4, 4) its last pose.
    """

    run_id: int
    map_id: int
    kf_id: int
    parent_id: int | None
    T_kf_parent: F64
    T_c_w: F64


@dataclass(frozen=True)
class LoopChecked:
    """Loop closing processed keyframe ``kf_id`` (loop detection, and correction when a loop was accepted).

    loop_kf_id: the keyframe the loop was closed with (None: no loop closed at this keyframe).
    essential_graph_edges: edges of the essential graph optimized (0 without a correction). timings_ms: per stage.
    record: loop closing's full account of the keyframe as plain containers (candidates, consistency, BoW matches,
    Sim3 inliers and scale, verification, pending hypotheses: the fields of
    ``slamkit.pipeline.outcomes.LoopOutcome``), what a run's loops.json lists.
    """

    run_id: int
    map_id: int
    kf_id: int
    loop_kf_id: int | None
    essential_graph_edges: int
    timings_ms: Mapping[str, float]
    record: Mapping[str, Any]


@dataclass(frozen=True)
class LoopClosed:
    """Loop closing accepted and corrected a loop between keyframes ``kf_id`` and ``loop_kf_id`` (ORB-SLAM VII).

    matches: map point matches of the loop; scale: the Sim3 correction's scale (1 up to drift);
    essential_graph_edges: edges of the essential graph optimized; timings_ms: per stage. Fired after the
    :class:`LoopChecked` of the same keyframe.
    """

    run_id: int
    map_id: int
    kf_id: int
    loop_kf_id: int
    matches: int
    scale: float
    essential_graph_edges: int
    timings_ms: Mapping[str, float]


@dataclass(frozen=True)
class MapsMerged:
    """Two maps of the Atlas were merged into one (ORB-SLAM3 map merging, slamkit/pipeline/map_merging.py).

    Fired by loop closing's thread when the merge moves the active map, before the welding BA. merged_map_id: the map
    that was absorbed (it leaves the Atlas); into_map_id: the active map, which holds the result under its id;
    kf_id / matched_kf_id: the current keyframe and the absorbed map's keyframe whose place recognition found the
    overlap. The merged map keeps the absorbed map's world frame: T_into_merged: (4, 4) the similarity x_new = T x_old
    that moved the into-map's entities from its previous world frame into that one (a Sim3 for monocular: scale in
    its rotation block); the absorbed map's entities keep their coordinates.
    """

    run_id: int
    merged_map_id: int
    into_map_id: int
    kf_id: int
    matched_kf_id: int
    T_into_merged: F64


@dataclass(frozen=True)
class MapSnapshot:
    """The map at the end of a run: its keyframes (time order not guaranteed: in id order) and its points.

    keyframe_ids: (K,) int64. keyframe_timestamps_s: (K,) s. T_c_w: (K, 4, 4) the keyframes' final poses;
    T_w_c: (K, 4, 4) their inverses. point_ids: (P,) int64 in id order; points_w: (P, 3) m, world frame.
    """

    map_id: int
    keyframe_ids: I64
    keyframe_timestamps_s: F64
    T_c_w: F64
    T_w_c: F64
    n_points: int
    point_ids: I64 = field(default_factory=lambda: np.zeros(0, np.int64))
    points_w: F64 = field(default_factory=lambda: np.zeros((0, 3)))

    @classmethod
    def of_store(cls, store: MapStore, map_id: int) -> MapSnapshot:
        """The store's keyframes (in id order) with their current poses, and its points."""
        kfs = [store.get_keyframe(k) for k in store.keyframe_ids()]
        point_ids = np.array(sorted(store.point_ids()), dtype=np.int64)
        return cls(
            map_id=map_id,
            keyframe_ids=np.array([kf.id for kf in kfs], dtype=np.int64),
            keyframe_timestamps_s=np.array([kf.timestamp_s for kf in kfs], dtype=np.float64),
            T_c_w=np.stack([kf.T_c_w for kf in kfs]) if kfs else np.zeros((0, 4, 4)),
            T_w_c=np.stack([kf.T_w_c for kf in kfs]) if kfs else np.zeros((0, 4, 4)),
            n_points=store.n_points(),
            point_ids=point_ids,
            points_w=store.point_rows(point_ids, "xyz_w").astype(np.float64) if point_ids.size else np.zeros((0, 3)),
        )

    @property
    def n_keyframes(self) -> int:
        return int(self.keyframe_ids.shape[0])

    def keyframe_poses(self) -> dict[int, F64]:
        """kf_id -> (4, 4) T_c_w."""
        return {int(k): self.T_c_w[i] for i, k in enumerate(self.keyframe_ids)}

    def keyframe_timestamps(self) -> dict[int, float]:
        """kf_id -> timestamp, s."""
        return {int(k): float(t) for k, t in zip(self.keyframe_ids, self.keyframe_timestamps_s, strict=True)}


@dataclass(frozen=True)
class RunFinished:
    """A run ended: after the last frame, after a failure, or after Ctrl-C (always fired once per run).

    status: "ok", "failed" or "interrupted". error: the exception that ended the run, one line per
    ``traceback.format_exception_only`` (None when ok). failed_thread: the pipeline thread whose exception
    stopped the run (threaded runner). maps: every map of the Atlas at the end, ascending ids. resets: map resets
    by tracking.
    wall_s: wall time of the run, s; sequence_s: time span of the frames played, s; frames_dropped: frames
    real-time playback dropped; realtime_factor: sequence over wall time (None when unknown); preloaded_mb:
    memory of frames read before playback, MiB. dropped_frames: the dropped frames, (frame index, timestamp s)
    each. source_end: how a live source's stream ended ("end of stream", "Ctrl-C", "dataset.duration_s=...",
    a read timeout; None for a recorded sequence).
    """

    run_id: int
    status: str
    error: str | None
    failed_thread: str | None
    maps: tuple[MapSnapshot, ...]
    resets: int
    wall_s: float
    sequence_s: float
    frames_dropped: int
    realtime_factor: float | None
    preloaded_mb: float
    dropped_frames: tuple[tuple[int, float], ...] = ()
    source_end: str | None = None
