"""ORB-SLAM sec. V-E: the new-keyframe decision (Tracking::NeedNewKeyFrame) as a pure function of a small record.

The tracker gathers the numbers (:class:`KeyFrameFacts`, read from the map under its read lock) and
:func:`decide_keyframe` applies the paper's four conditions to them, so each condition can be tested on its own:

1. more than ``keyframe_min_frames_since_reloc`` frames since the last relocalization (unless the map is small);
2. local mapping is idle, or more than ``keyframe_max_frames_idle`` frames passed since the last keyframe;
3. the frame tracks at least ``keyframe_min_tracked_points`` points;
4. it tracks fewer than ``keyframe_max_ref_ratio`` of the reference keyframe's points.

When only condition 2 fails the answer is MAPPING_BUSY: the runner acts on it (the paper: "a signal is sent to stop
local BA"). While local mapping is parked for a loop correction no keyframe is made (MAPPING_STOPPED).
"""

from __future__ import annotations

from dataclasses import dataclass

from slamkit.pipeline.config import TrackingConfig
from slamkit.pipeline.outcomes import KeyFrameDecision, MappingState


@dataclass(frozen=True)
class KeyFrameFacts:
    """What the keyframe decision needs about one tracked frame.

    frame_index / last_keyframe_frame_index / last_relocalization_frame_index: frame numbers (a large negative
    number when there was none). tracked_points: map points the frame tracks after V-D. reference_tracked_points:
    the reference keyframe's points seen by at least ``keyframe_ref_min_observations`` keyframes (None: no
    reference keyframe in the map). keyframes_in_map: the map's size. mapping: local mapping's state.
    """

    frame_index: int
    last_keyframe_frame_index: int
    last_relocalization_frame_index: int
    tracked_points: int
    reference_tracked_points: int | None
    keyframes_in_map: int
    mapping: MappingState


def decide_keyframe(facts: KeyFrameFacts, cfg: TrackingConfig) -> KeyFrameDecision:
    """V-E's four conditions (see the module docstring) -> INSERT, NOT_NEEDED, MAPPING_BUSY or MAPPING_STOPPED."""
    if not facts.mapping.accepting_keyframes:
        return KeyFrameDecision.MAPPING_STOPPED
    recently_relocalized = facts.frame_index < facts.last_relocalization_frame_index + cfg.keyframe_min_frames_since_reloc
    if recently_relocalized and facts.keyframes_in_map > cfg.keyframe_min_frames_since_reloc:
        return KeyFrameDecision.NOT_NEEDED  # condition 1
    if facts.tracked_points < cfg.keyframe_min_tracked_points:
        return KeyFrameDecision.NOT_NEEDED  # condition 3
    ref = facts.reference_tracked_points
    if ref is not None and facts.tracked_points >= cfg.keyframe_max_ref_ratio * ref:
        return KeyFrameDecision.NOT_NEEDED  # condition 4
    if facts.mapping.idle or facts.frame_index >= facts.last_keyframe_frame_index + cfg.keyframe_max_frames_idle:
        return KeyFrameDecision.INSERT  # condition 2
    return KeyFrameDecision.MAPPING_BUSY


def reference_min_observations(keyframes_in_map: int, cfg: TrackingConfig) -> int:
    """Observations a reference keyframe's point needs to count in condition 4 (ORB-SLAM nMinObs: 3, or 2 while the
    map has at most two keyframes)."""
    return cfg.keyframe_ref_min_observations_small_map if keyframes_in_map <= 2 else cfg.keyframe_ref_min_observations
