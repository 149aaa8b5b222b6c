"""ORB-SLAM sec. V-E: the new-keyframe decision as ORB-SLAM2's released code (Tracking::NeedNewKeyFrame, monocular; the
same in ORB-SLAM3), a pure function of a small record. Stereo/RGB-D frames (``KeyFrameFacts.stereo``) follow the
code's non-monocular branch: thRefRatio 0.75 (0.4 with one keyframe), c1c (fewer than 25% of the reference's points)
and the close-point condition (fewer than 100 close points tracked, more than 70 untracked).

The tracker gathers the numbers (:class:`KeyFrameFacts`, read from the map under its read lock) and
:func:`decide_keyframe` applies the code's conditions to them, so each can be tested on its own. ``max_frames`` is
the code's mMaxFrames, the camera's frame rate (``keyframe_max_frames``; 0 = the dataset's fps):

- no keyframe within ``max_frames`` frames of a relocalization, unless the map holds at most ``max_frames``
  keyframes (the paper's condition 1, 20 frames);
- c1a: at least ``max_frames`` frames since the last keyframe, or c1b: local mapping is idle (mMinFrames = 0) —
  or will be before the next frame, when the runner waits for it (``MappingState.waits_for_idle``: a recorded
  sequence read as fast as possible has no frame period);
- c2: the frame tracks fewer than ``keyframe_max_ref_ratio`` (0.9 monocular) of the reference keyframe's points and
  more than ``keyframe_min_tracked_points`` (15; the paper's condition 3 says 50);
- (c1a or c1b) and c2: a keyframe if local mapping is idle; otherwise MAPPING_BUSY — ORB-SLAM's monocular tracking
  then only interrupts local BA and makes no keyframe (the runner acts on it: docs/runtime.md).

While local mapping is parked for a loop correction no keyframe is made (MAPPING_STOPPED).
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
    reference keyframe in the map). keyframes_in_map: the map's size. mapping: local mapping's state. max_frames:
    ORB-SLAM's mMaxFrames (frames), the camera's frame rate unless ``keyframe_max_frames`` sets it.
    stereo: the frame has depth (stereo or RGB-D sensor). close_tracked / close_untracked: its close keypoints
    (depth below th_depth_m) with / without a tracked map point (ORB-SLAM2 nTrackedClose / nNonTrackedClose).
    """

    frame_index: int
    last_keyframe_frame_index: int
    last_relocalization_frame_index: int
    tracked_points: int
    reference_tracked_points: int | None
    keyframes_in_map: int
    mapping: MappingState
    max_frames: int = 30
    stereo: bool = False
    close_tracked: int = 0
    close_untracked: int = 0


def decide_keyframe(facts: KeyFrameFacts, cfg: TrackingConfig) -> KeyFrameDecision:
    """ORB-SLAM2's NeedNewKeyFrame (see the module docstring) -> INSERT, NOT_NEEDED, MAPPING_BUSY or
    MAPPING_STOPPED."""
    if not facts.mapping.accepting_keyframes:
        return KeyFrameDecision.MAPPING_STOPPED
    max_frames = facts.max_frames
    recently_relocalized = facts.frame_index < facts.last_relocalization_frame_index + max_frames
    if recently_relocalized and facts.keyframes_in_map > max_frames:
        return KeyFrameDecision.NOT_NEEDED
    c1a = facts.frame_index >= facts.last_keyframe_frame_index + max_frames
    c1b = facts.mapping.idle or facts.mapping.waits_for_idle
    ref = facts.reference_tracked_points
    if facts.stereo:
        # ORB-SLAM2 NeedNewKeyFrame, mSensor != MONOCULAR: thRefRatio 0.75 (0.4 with one keyframe), c1c, and the
        # close-point condition bNeedToInsertClose
        ratio = (
            cfg.keyframe_max_ref_ratio_stereo_single
            if facts.keyframes_in_map < 2
            else cfg.keyframe_max_ref_ratio_stereo
        )
        need_close = (
            facts.close_tracked < cfg.keyframe_close_tracked_max
            and facts.close_untracked > cfg.keyframe_close_untracked_min
        )
        c1c = ref is None or facts.tracked_points < cfg.keyframe_c1c_ref_ratio_stereo * ref or need_close
        few = ref is None or facts.tracked_points < ratio * ref or need_close
        c2 = few and facts.tracked_points > cfg.keyframe_min_tracked_points
        if not ((c1a or c1b or c1c) and c2):
            return KeyFrameDecision.NOT_NEEDED
        # ORB-SLAM2 inserts a stereo keyframe while local mapping is busy when fewer than 3 are queued; slamkit's
        # runner interrupts local BA or waits for local mapping, then makes it (MAPPING_BUSY)
        return KeyFrameDecision.INSERT if facts.mapping.idle else KeyFrameDecision.MAPPING_BUSY
    few_of_reference = ref is None or facts.tracked_points < cfg.keyframe_max_ref_ratio * ref
    c2 = few_of_reference and facts.tracked_points > cfg.keyframe_min_tracked_points
    if not ((c1a or c1b) and c2):
        return KeyFrameDecision.NOT_NEEDED
    return KeyFrameDecision.INSERT if facts.mapping.idle else KeyFrameDecision.MAPPING_BUSY


def max_frames_of(cfg: TrackingConfig, fps: float) -> int:
    """ORB-SLAM's mMaxFrames: ``keyframe_max_frames`` when set (> 0), else the camera's frame rate ``fps`` (Hz)
    rounded (ORB-SLAM2 Tracking: mMaxFrames = Camera.fps, 30 when the settings give none)."""
    if cfg.keyframe_max_frames > 0:
        return int(cfg.keyframe_max_frames)
    return max(1, round(fps)) if fps > 0 else 30


def reference_min_observations(keyframes_in_map: int, cfg: TrackingConfig) -> int:
    """Observations a reference keyframe's point needs to count in condition 4 (ORB-SLAM nMinObs: 3, or 2 while the
    map has at most two keyframes)."""
    return cfg.keyframe_ref_min_observations_small_map if keyframes_in_map <= 2 else cfg.keyframe_ref_min_observations
