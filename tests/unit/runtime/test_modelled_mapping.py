"""The sequential runner's model of a busy local mapping (``runner.modelled_mapping_ms``, ModelledMapping): after a
keyframe at timestamp t, frames before t + the modelled time see local mapping busy, and a monocular frame then gets
no keyframe (ORB-SLAM2/3's NeedNewKeyFrame); frames after it see it idle and get their keyframe."""

from __future__ import annotations

import pytest

from slamkit.errors import ConfigError
from slamkit.pipeline.config import TrackingConfig
from slamkit.pipeline.outcomes import KeyFrameDecision
from slamkit.pipeline.tracking.keyframe_decision import KeyFrameFacts, decide_keyframe
from slamkit.runtime.modelled_mapping import ModelledMapping
from slamkit.runtime.sequential import SequentialRunner


def _wanted_keyframe(model: ModelledMapping, timestamp_s: float, frame_index: int) -> KeyFrameDecision:
    """The decision for a monocular frame that wants a keyframe (c2 holds, 3 frames after the last keyframe, so c1a
    does not), tracked with the model's state at ``timestamp_s``."""
    facts = KeyFrameFacts(
        frame_index=frame_index,
        last_keyframe_frame_index=frame_index - 3,
        last_relocalization_frame_index=-(10**9),
        tracked_points=100,
        reference_tracked_points=200,
        keyframes_in_map=40,
        mapping=model.state(timestamp_s),
        max_frames=30,
    )
    return decide_keyframe(facts, TrackingConfig())


def test_a_keyframe_is_refused_while_mapping_is_modelled_busy_and_made_after() -> None:
    model = ModelledMapping(busy_s=0.2)
    assert model.state(10.0).idle  # nothing made yet
    model.keyframes_made(10.0, 1)
    # a 30 Hz camera's frames 0.1 and 0.167 s later: busy, no keyframe (monocular: not even a queued one)
    assert _wanted_keyframe(model, 10.1, 1003) == KeyFrameDecision.NOT_NEEDED
    assert _wanted_keyframe(model, 10.167, 1005) == KeyFrameDecision.NOT_NEEDED
    # 0.2 s after the keyframe local mapping is done: the keyframe is made
    assert _wanted_keyframe(model, 10.2, 1006) == KeyFrameDecision.INSERT
    assert _wanted_keyframe(model, 10.4, 1012) == KeyFrameDecision.INSERT


def test_the_time_is_sequence_time_per_keyframe_queued_behind_the_earlier_ones() -> None:
    model = ModelledMapping(busy_s=0.3)
    model.keyframes_made(1.0, 2)  # a new map's two keyframes: 0.6 s of work
    assert not model.state(1.59).idle and model.state(1.61).idle
    model.keyframes_made(1.5, 1)  # made while busy (c1a, or a caller that ignores the state): queued behind them
    assert not model.state(1.89).idle and model.state(1.91).idle
    model.keyframes_made(5.0, 0)  # no keyframe: nothing changes
    assert model.state(2.0).idle
    model.reset()  # a map reset empties local mapping's queue
    model.keyframes_made(3.0, 1)
    assert not model.state(3.29).idle and model.state(3.31).idle


def test_zero_is_always_idle_and_a_negative_time_is_refused() -> None:
    model = ModelledMapping(busy_s=0.0)
    model.keyframes_made(1.0, 2)
    assert model.state(1.0).idle and model.state(1.01).idle
    with pytest.raises(ConfigError, match="modelled_mapping_ms"):
        SequentialRunner(None, None, None, modelled_mapping_ms=-1.0)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="modelled_mapping_new_map_ms"):
        SequentialRunner(None, None, None, modelled_mapping_new_map_ms=float("nan"))  # type: ignore[arg-type]


def test_a_new_maps_keyframes_can_cost_their_own_time() -> None:
    # ORB-SLAM's local mapping runs no local BA on a new map's two keyframes: modelled_mapping_new_map_ms=0
    model = ModelledMapping(busy_s=0.2, new_map_busy_s=0.0)
    model.keyframes_made(0.17, 2, new_map=True)
    assert model.state(0.20).idle  # the next frame may become a keyframe, as ORB-SLAM3's does on fr1_xyz
    model.keyframes_made(0.20, 1)
    assert not model.state(0.39).idle and model.state(0.41).idle
    # None: a new map's keyframes cost the same as the others
    model = ModelledMapping(busy_s=0.2)
    model.keyframes_made(0.17, 2, new_map=True)
    assert not model.state(0.56).idle and model.state(0.58).idle


def _stamp(i: int, fps: int, origin: float, stamps: str) -> float:
    """Frame i's timestamp, s, from a camera at ``fps`` started at ``origin``: an epoch origin written with six
    decimals (TUM) and parsed as a float; else i / fps as a float sum ("float") or rounded to ns and read back ("ns")."""
    if origin > 0.0:
        return float(f"{origin + round(i * 1e6 / fps) / 1e6:.6f}")
    if stamps == "float":
        return origin + i / fps
    return round((origin + i / fps) * 1e9) / 1e9


@pytest.mark.parametrize("fps", [10, 15, 20, 25, 30, 60])
def test_a_frame_exactly_at_the_end_sees_local_mapping_idle_whether_its_stamp_is_a_float_sum_or_integer_ns(
    fps: int,
) -> None:
    """The model compares in integer microseconds: a frame captured exactly when the modelled work ends (a 30 Hz
    camera's third frame after a keyframe with 100 ms) sees local mapping idle whatever float rounding the
    timestamps carry — i / fps (the synthetic room), the same rounded to ns and read back (a ROS bag), or an epoch time
    written with six decimals (TUM's 1.3e9 s stamps, whose float spacing is 2.4e-7 s). The frame before it sees it
    busy. (An epoch stamp in ns that is not a whole us, read as a float, carries 0.24 us of rounding: not covered.)"""
    busy_s = 0.1
    period_ns = round(1e9 / fps)
    for first in range(0, 40):
        for origin in (0.0, 1305031102.175304):
            for stamps in ("float", "ns"):

                def t(i: int, origin: float = origin, stamps: str = stamps) -> float:
                    return _stamp(i, fps, origin, stamps)

                model = ModelledMapping(busy_s=busy_s)
                model.keyframes_made(t(first), 1)
                # the frames of the modelled time: busy; the first at or past its end: idle
                after = [i for i in range(first + 1, first + 20) if (i - first) * period_ns >= busy_s * 1e9 - 1e3]
                for i in range(first + 1, after[0]):
                    assert not model.state(t(i)).idle, (fps, first, origin, stamps, i)
                assert model.state(t(after[0])).idle, (fps, first, origin, stamps, after[0])
