"""The records the pipeline's steps and the runners exchange: what tracking, local mapping and loop closing did
with one frame or keyframe (their *outcomes*), and what the runner tells tracking about local mapping
(:class:`MappingState`).

They live here, not in the algorithm modules, so that a runner, the run log, the lifecycle events and the
evaluation read them without importing an algorithm, and an algorithm's module holds only its algorithm. Each
record is plain data: ids, counts, (4, 4) poses ``T_c_w`` (world to camera, metres), timings in ms.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from slamkit.pipeline.lost import LostDecision

if TYPE_CHECKING:
    from slamkit.map.entities import KeyFrame

F64 = NDArray[np.float64]


class TrackingState(StrEnum):
    NOT_INITIALIZED = "not_initialized"
    OK = "ok"
    LOST = "lost"


class KeyFrameDecision(StrEnum):
    """Tracking's new-keyframe decision for one frame (ORB-SLAM V-E, slamkit/pipeline/tracking/keyframe_decision.py).

    INSERT: the frame became a keyframe (in ``TrackingOutcome.new_keyframes``). NOT_NEEDED: condition 1, 3 or 4
    fails (or the frame was not tracked). MAPPING_STOPPED: local mapping is parked for a loop correction and
    accepts no keyframe (ORB-SLAM NeedNewKeyFrame: ``isStopped() || stopRequested()``). MAPPING_BUSY: a keyframe is
    wanted but condition 2 fails (local mapping busy, too few frames since the last keyframe): the runner acts on
    it (real time: stop the running local BA; as fast as possible: wait for local mapping, then
    ``Tracker.make_keyframe``; docs/runtime.md).
    """

    INSERT = "insert"
    NOT_NEEDED = "not_needed"
    MAPPING_STOPPED = "mapping_stopped"
    MAPPING_BUSY = "mapping_busy"


@dataclass(frozen=True)
class MappingState:
    """Local mapping's state as the runner sees it when a frame is tracked (ORB-SLAM: ``AcceptKeyFrames`` and
    ``isStopped``/``stopRequested``), given to ``Tracker.step`` as data.

    idle: nothing queued and no keyframe in progress (V-E condition 2). accepting_keyframes: False while local
    mapping is parked (or asked to park) for a loop correction: tracking then makes no keyframe. waits_for_idle:
    frames do not arrive on a clock — the runner waits for a busy local mapping rather than dropping the keyframe
    (the threaded runner as fast as possible). A camera's frame period gives local mapping time to finish; a
    recorded sequence read as fast as possible gives it none, so without this the keyframe decision's "mapping is
    idle" (c1b) would almost never hold and the map would get a keyframe only every ``max_frames`` frames.
    """

    idle: bool = True
    accepting_keyframes: bool = True
    waits_for_idle: bool = False


@dataclass
class TrackingOutcome:
    """What tracking did with one frame.

    T_c_w: (4, 4) estimated pose (None when not tracked). inliers: map points matched after the last pose
    optimization. new_keyframes: keyframes made from this frame, for local mapping: the tracked frame's keyframe
    (not in the map yet: local mapping inserts it), or the two keyframes of a new map (``initialized_map``: put in
    the map by initialisation, local mapping processes them next); once the runner has handed them over it calls
    ``release_keyframes``, so the run log, which keeps every outcome, does not keep every keyframe ever made alive
    (about 0.3 MB each: features and bag of words; most are culled later); ``keyframe_ids`` names them before and
    after. keyframe: the V-E decision. reference_kf_id /
    T_ref_w: the keyframe the frame's pose is recorded against and its (4, 4) T_c_w as tracking last read it (the
    frame's own pose when it became that keyframe), so a runner never needs a keyframe local mapping has not
    inserted yet. lost_decision: on a frame tracking could not track, what to do (slamkit/pipeline/lost.py,
    ORB-SLAM3): RELOCALIZE keeps trying; RESET_MAP (a map too small to keep) and NEW_MAP (relocalization failed for
    too long: the map stays in the Atlas) are carried out by the runner, which parks the workers and calls
    ``Tracker.reset`` / ``Tracker.start_new_map``; None when the frame was not lost. timings_ms: per stage.
    """

    frame_index: int
    timestamp_s: float
    state: TrackingState
    T_c_w: F64 | None
    n_features: int
    inliers: int
    method: str
    new_keyframes: list[KeyFrame] = field(default_factory=list)
    initialized_map: bool = False
    keyframe: KeyFrameDecision = KeyFrameDecision.NOT_NEEDED
    reference_kf_id: int | None = None
    T_ref_w: F64 | None = None
    lost_decision: LostDecision | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)
    message: str = ""
    map_moves: int = 0  # how many moves of the active map (merges) its poses are after (Tracker.follow_map_moves)
    released_keyframe_ids: tuple[int, ...] = ()  # new_keyframes' ids after release_keyframes

    @property
    def keyframe_ids(self) -> tuple[int, ...]:
        """Ids of the keyframes made from this frame (``new_keyframes``), also after ``release_keyframes``."""
        return tuple(kf.id for kf in self.new_keyframes) or self.released_keyframe_ids

    def release_keyframes(self) -> None:
        """Drop the keyframe objects once local mapping has them, keeping their ids (``keyframe_ids``)."""
        if self.new_keyframes:
            self.released_keyframe_ids = tuple(kf.id for kf in self.new_keyframes)
            self.new_keyframes = []


@dataclass(frozen=True)
class CulledKeyFrame:
    """A keyframe removed by culling, kept as a pose relative to its spanning-tree parent so frames that
    referred to it can still be placed (ORB-SLAM keeps Tcp for the same reason)."""

    kf_id: int
    parent_id: int | None
    T_kf_parent: F64
    T_c_w: F64


@dataclass
class MappingOutcome:
    """What local mapping did with one keyframe (counts and per-stage times in ms). ba_due: the keyframe was due a
    local BA (it is on, the map has more than two keyframes); ba_skipped: it was due but a newer keyframe's abort
    came before it started; ba_aborted: it started and was stopped early (ORB-SLAM's mbAbortBA)."""

    kf_id: int
    points_culled: int = 0
    points_created: int = 0
    points_fused: int = 0
    ba_outliers: int = 0
    ba_due: bool = False
    ba_skipped: bool = False
    ba_aborted: bool = False
    culled_keyframes: list[CulledKeyFrame] = field(default_factory=list)
    timings_ms: dict[str, float] = field(default_factory=dict)


@dataclass
class LoopOutcome:
    """What loop closing did with one keyframe.

    tried: one record per consistent candidate (BoW matches, Sim3 inliers, loop matches, and its geometric
    verification: ``correction_rotation_deg`` the turn the loop would give the map, ``verification`` each
    keyframe's check, ``agreeing`` the covisible keyframes that agreed; ``rejected`` says why). pending: the check
    of a pending loop hypothesis in this keyframe (ORB-SLAM3's confirmation by the next keyframes), with its state:
    "agreed", "accepted", "missed" or "dropped". loop_kf_id: the loop keyframe of an accepted loop (its correction
    follows: ``LoopCloser.correct``). merge_candidates: place-recognition candidates in other maps of the Atlas
    (ORB-SLAM3 DetectNBestCandidates' merge candidates: the same machinery, a match in another map is a merge
    candidate); merge_tried / merge_pending: their verification, recorded as ``tried`` / ``pending`` (each record also
    names the candidate's ``map``); merge_kf_id / merge_map_id / merge_matches / merge_scale: an accepted merge (the
    matched keyframe, its map, the refined matches, the Sim3's scale), merged by ``LoopCloser.merge``; after the merge
    merge_imported_keyframes / merge_fused / merge_ba_outliers its counts and merge_transform the (4, 4) similarity
    x_new = G x_old that moved the active map into the matched map's frame (None: no merge done).
    """

    kf_id: int
    candidates: list[int] = field(default_factory=list)
    consistent: list[int] = field(default_factory=list)
    tried: list[dict[str, object]] = field(default_factory=list)
    merge_candidates: list[int] = field(default_factory=list)
    merge_tried: list[dict[str, object]] = field(default_factory=list)
    merge_pending: dict[str, object] | None = None
    merge_kf_id: int | None = None
    merge_map_id: int | None = None
    merge_matches: int = 0
    merge_scale: float = 1.0
    merge_imported_keyframes: int = 0
    merge_fused: int = 0
    merge_ba_outliers: int = 0
    merge_transform: list[list[float]] | None = None
    pending: dict[str, object] | None = None
    loop_kf_id: int | None = None
    matches: int = 0
    scale: float = 1.0
    essential_graph_edges: int = 0
    timings_ms: dict[str, float] = field(default_factory=dict)
    reason: str = ""


__all__ = [
    "CulledKeyFrame",
    "KeyFrameDecision",
    "LoopOutcome",
    "MappingOutcome",
    "MappingState",
    "TrackingOutcome",
    "TrackingState",
]
