"""The new-keyframe decision (ORB-SLAM V-E) as ORB-SLAM2's released NeedNewKeyFrame, a pure function: each of the
code's conditions (mMaxFrames = the camera's fps, c1a/c1b/c2), and local mapping's state given as data (busy: the
runner is told; parked for a loop correction: no keyframe)."""

from __future__ import annotations

import dataclasses

import pytest

from slamkit.pipeline.config import TrackingConfig
from slamkit.pipeline.outcomes import KeyFrameDecision, MappingState
from slamkit.pipeline.tracking.keyframe_decision import (
    KeyFrameFacts,
    decide_keyframe,
    max_frames_of,
    reference_min_observations,
)

CFG = TrackingConfig()
IDLE = MappingState(idle=True, accepting_keyframes=True)
BUSY = MappingState(idle=False, accepting_keyframes=True)
STOPPED = MappingState(idle=False, accepting_keyframes=False)

#: A frame that passes every condition: far from the last relocalization, 5 frames after the last keyframe, tracking
#: 100 points of a reference keyframe with 200, in a map of 40 keyframes, local mapping idle, a 30 Hz camera.
GOOD = KeyFrameFacts(
    frame_index=1000,
    last_keyframe_frame_index=995,
    last_relocalization_frame_index=-(10**9),
    tracked_points=100,
    reference_tracked_points=200,
    keyframes_in_map=40,
    mapping=IDLE,
    max_frames=30,
)


def facts(**changes: object) -> KeyFrameFacts:
    return dataclasses.replace(GOOD, **changes)  # type: ignore[arg-type]


def test_a_frame_passing_every_condition_becomes_a_keyframe() -> None:
    assert decide_keyframe(GOOD, CFG) == KeyFrameDecision.INSERT


def test_no_keyframe_within_max_frames_of_a_relocalization_unless_the_map_is_small() -> None:
    assert decide_keyframe(facts(last_relocalization_frame_index=980), CFG) == KeyFrameDecision.NOT_NEEDED
    assert decide_keyframe(facts(last_relocalization_frame_index=970), CFG) == KeyFrameDecision.INSERT  # 30 frames
    # ORB-SLAM: unless the map is small (at most mMaxFrames keyframes)
    assert decide_keyframe(facts(last_relocalization_frame_index=990, keyframes_in_map=30), CFG) == (
        KeyFrameDecision.INSERT
    )
    # a 10 Hz camera (KITTI): 10 frames
    assert decide_keyframe(facts(last_relocalization_frame_index=990, max_frames=10), CFG) == KeyFrameDecision.INSERT


def test_busy_local_mapping_is_told_to_the_runner_after_max_frames() -> None:
    # c1b fails while mapping is busy, c1a holds after mMaxFrames; monocular ORB-SLAM then only interrupts local BA
    assert decide_keyframe(facts(mapping=BUSY), CFG) == KeyFrameDecision.NOT_NEEDED
    assert decide_keyframe(facts(mapping=BUSY, last_keyframe_frame_index=970), CFG) == KeyFrameDecision.MAPPING_BUSY
    # the other conditions come first: a keyframe nobody wants is not "busy"
    assert decide_keyframe(facts(mapping=BUSY, tracked_points=10), CFG) == KeyFrameDecision.NOT_NEEDED


def test_a_runner_that_waits_for_local_mapping_gets_busy_whenever_a_keyframe_is_wanted() -> None:
    # as fast as possible there is no frame period for local mapping to finish in: the runner waits for it, so c1b
    # holds as it would with a camera, and a busy local mapping is reported at once (not only after mMaxFrames)
    waiting = MappingState(idle=False, accepting_keyframes=True, waits_for_idle=True)
    assert decide_keyframe(facts(mapping=waiting), CFG) == KeyFrameDecision.MAPPING_BUSY
    assert decide_keyframe(facts(mapping=dataclasses.replace(waiting, idle=True)), CFG) == KeyFrameDecision.INSERT
    assert decide_keyframe(facts(mapping=waiting, tracked_points=180), CFG) == KeyFrameDecision.NOT_NEEDED
    stopped = MappingState(idle=False, accepting_keyframes=False, waits_for_idle=True)
    assert decide_keyframe(facts(mapping=stopped), CFG) == KeyFrameDecision.MAPPING_STOPPED


def test_c2_more_than_15_tracked_points() -> None:
    assert decide_keyframe(facts(tracked_points=15, reference_tracked_points=100), CFG) == KeyFrameDecision.NOT_NEEDED
    assert decide_keyframe(facts(tracked_points=16, reference_tracked_points=100), CFG) == KeyFrameDecision.INSERT


def test_c2_fewer_than_90_percent_of_the_reference_keyframes_points() -> None:
    assert decide_keyframe(facts(tracked_points=180), CFG) == KeyFrameDecision.NOT_NEEDED
    assert decide_keyframe(facts(tracked_points=179), CFG) == KeyFrameDecision.INSERT
    assert decide_keyframe(facts(tracked_points=1000, reference_tracked_points=None), CFG) == KeyFrameDecision.INSERT


def test_no_keyframe_while_local_mapping_is_stopped_for_a_loop_correction() -> None:
    assert decide_keyframe(facts(mapping=STOPPED), CFG) == KeyFrameDecision.MAPPING_STOPPED
    assert decide_keyframe(facts(mapping=MappingState(idle=True, accepting_keyframes=False)), CFG) == (
        KeyFrameDecision.MAPPING_STOPPED
    )


def test_max_frames_is_the_camera_frame_rate_unless_configured() -> None:
    assert max_frames_of(CFG, 30.0) == 30
    assert max_frames_of(CFG, 9.65) == 10  # KITTI
    assert max_frames_of(CFG, 0.0) == 30  # no rate known: ORB-SLAM's default
    assert max_frames_of(dataclasses.replace(CFG, keyframe_max_frames=20), 30.0) == 20


@pytest.mark.parametrize(
    ("field", "value", "case", "expected"),
    [
        ("keyframe_min_tracked_points", 101, {}, KeyFrameDecision.NOT_NEEDED),
        ("keyframe_max_ref_ratio", 0.5, {}, KeyFrameDecision.NOT_NEEDED),
    ],
)
def test_each_threshold_is_read_from_the_config(
    field: str, value: float, case: dict[str, object], expected: KeyFrameDecision
) -> None:
    assert decide_keyframe(facts(**case), CFG) != expected
    assert decide_keyframe(facts(**case), dataclasses.replace(CFG, **{field: value})) == expected


def test_reference_points_need_three_observations_or_two_in_a_map_of_two_keyframes() -> None:
    assert reference_min_observations(2, CFG) == 2
    assert reference_min_observations(3, CFG) == 3
    assert reference_min_observations(3, dataclasses.replace(CFG, keyframe_ref_min_observations=4)) == 4


# ---- stereo / RGB-D (ORB-SLAM2 NeedNewKeyFrame, mSensor != MONOCULAR) ---------------------------------------


def stereo(**changes: object) -> KeyFrameFacts:
    """A stereo frame tracking 180 of the reference's 200 points (90%: no keyframe by the 0.75 ratio), 150 of its
    close points tracked, 20 untracked, mapping busy and 5 frames after the last keyframe (c1a, c1b fail)."""
    base = facts(tracked_points=180, mapping=BUSY, stereo=True, close_tracked=150, close_untracked=20)
    return dataclasses.replace(base, **changes)  # type: ignore[arg-type]


def test_stereo_uses_the_075_ratio_and_04_with_a_single_keyframe() -> None:
    idle = stereo(mapping=IDLE)
    assert decide_keyframe(idle, CFG) == KeyFrameDecision.NOT_NEEDED  # 180 >= 0.75 * 200
    assert decide_keyframe(dataclasses.replace(idle, tracked_points=149), CFG) == KeyFrameDecision.INSERT
    # the monocular 0.9 would have asked for one at 170 tracked points; stereo does not
    assert decide_keyframe(dataclasses.replace(idle, tracked_points=170), CFG) == KeyFrameDecision.NOT_NEEDED
    assert decide_keyframe(dataclasses.replace(idle, tracked_points=170, stereo=False), CFG) == (
        KeyFrameDecision.INSERT
    )
    one = dataclasses.replace(idle, keyframes_in_map=1, tracked_points=100)
    assert decide_keyframe(one, CFG) == KeyFrameDecision.NOT_NEEDED  # 100 >= 0.4 * 200
    assert decide_keyframe(dataclasses.replace(one, tracked_points=79), CFG) == KeyFrameDecision.INSERT


def test_stereo_close_point_condition_asks_for_a_keyframe_while_mapping_is_busy() -> None:
    """Fewer than 100 close points tracked and more than 70 untracked: c1c and c2 hold even with 90% of the reference
    tracked and local mapping busy (the runner then interrupts local BA and makes it: MAPPING_BUSY)."""
    assert decide_keyframe(stereo(), CFG) == KeyFrameDecision.NOT_NEEDED
    need = stereo(close_tracked=99, close_untracked=71)
    assert decide_keyframe(need, CFG) == KeyFrameDecision.MAPPING_BUSY
    assert decide_keyframe(dataclasses.replace(need, mapping=IDLE), CFG) == KeyFrameDecision.INSERT
    assert decide_keyframe(stereo(close_tracked=100, close_untracked=71), CFG) == KeyFrameDecision.NOT_NEEDED
    assert decide_keyframe(stereo(close_tracked=99, close_untracked=70), CFG) == KeyFrameDecision.NOT_NEEDED
    # c1c's other half: fewer than 25% of the reference's points
    assert decide_keyframe(stereo(tracked_points=49), CFG) == KeyFrameDecision.MAPPING_BUSY
    # at most 15 tracked points: never
    assert decide_keyframe(stereo(tracked_points=15, close_tracked=0, close_untracked=300), CFG) == (
        KeyFrameDecision.NOT_NEEDED
    )
