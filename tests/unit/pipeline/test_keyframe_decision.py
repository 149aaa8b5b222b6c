"""The new-keyframe decision (ORB-SLAM V-E) as a pure function: each of the paper's four conditions, and local
mapping's state given as data (busy: the runner is told; parked for a loop correction: no keyframe)."""

from __future__ import annotations

import dataclasses

import pytest

from slamkit.pipeline.config import TrackingConfig
from slamkit.pipeline.outcomes import KeyFrameDecision, MappingState
from slamkit.pipeline.tracking.keyframe_decision import KeyFrameFacts, decide_keyframe, reference_min_observations

CFG = TrackingConfig()
IDLE = MappingState(idle=True, accepting_keyframes=True)
BUSY = MappingState(idle=False, accepting_keyframes=True)
STOPPED = MappingState(idle=False, accepting_keyframes=False)

#: A frame that passes every condition: far from the last relocalization, 5 frames after the last keyframe, tracking
#: 100 points of a reference keyframe with 200, in a map of 30 keyframes, local mapping idle.
GOOD = KeyFrameFacts(
    frame_index=1000,
    last_keyframe_frame_index=995,
    last_relocalization_frame_index=-(10**9),
    tracked_points=100,
    reference_tracked_points=200,
    keyframes_in_map=30,
    mapping=IDLE,
)


def facts(**changes: object) -> KeyFrameFacts:
    return dataclasses.replace(GOOD, **changes)  # type: ignore[arg-type]


def test_a_frame_passing_every_condition_becomes_a_keyframe() -> None:
    assert decide_keyframe(GOOD, CFG) == KeyFrameDecision.INSERT


def test_condition_1_no_keyframe_within_20_frames_of_a_relocalization() -> None:
    assert decide_keyframe(facts(last_relocalization_frame_index=990), CFG) == KeyFrameDecision.NOT_NEEDED
    assert decide_keyframe(facts(last_relocalization_frame_index=980), CFG) == KeyFrameDecision.INSERT  # 20 frames
    # ORB-SLAM: unless the map is small (at most mMaxFrames keyframes)
    assert decide_keyframe(facts(last_relocalization_frame_index=990, keyframes_in_map=20), CFG) == (
        KeyFrameDecision.INSERT
    )


def test_condition_2_busy_local_mapping_is_told_to_the_runner_unless_20_frames_passed() -> None:
    assert decide_keyframe(facts(mapping=BUSY), CFG) == KeyFrameDecision.MAPPING_BUSY
    assert decide_keyframe(facts(mapping=BUSY, last_keyframe_frame_index=980), CFG) == KeyFrameDecision.INSERT
    # the other conditions come first: a keyframe nobody wants is not "busy"
    assert decide_keyframe(facts(mapping=BUSY, tracked_points=10), CFG) == KeyFrameDecision.NOT_NEEDED


def test_condition_3_at_least_50_tracked_points() -> None:
    assert decide_keyframe(facts(tracked_points=49, reference_tracked_points=100), CFG) == KeyFrameDecision.NOT_NEEDED
    assert decide_keyframe(facts(tracked_points=50, reference_tracked_points=100), CFG) == KeyFrameDecision.INSERT


def test_condition_4_fewer_than_90_percent_of_the_reference_keyframes_points() -> None:
    assert decide_keyframe(facts(tracked_points=180), CFG) == KeyFrameDecision.NOT_NEEDED
    assert decide_keyframe(facts(tracked_points=179), CFG) == KeyFrameDecision.INSERT
    assert decide_keyframe(facts(tracked_points=1000, reference_tracked_points=None), CFG) == KeyFrameDecision.INSERT


def test_no_keyframe_while_local_mapping_is_stopped_for_a_loop_correction() -> None:
    assert decide_keyframe(facts(mapping=STOPPED), CFG) == KeyFrameDecision.MAPPING_STOPPED
    assert decide_keyframe(facts(mapping=MappingState(idle=True, accepting_keyframes=False)), CFG) == (
        KeyFrameDecision.MAPPING_STOPPED
    )


@pytest.mark.parametrize(
    ("field", "value", "case", "expected"),
    [
        ("keyframe_min_frames_since_reloc", 5, {"last_relocalization_frame_index": 990}, KeyFrameDecision.INSERT),
        ("keyframe_max_frames_idle", 5, {"mapping": BUSY}, KeyFrameDecision.INSERT),
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
