"""A deterministic model of how long local mapping is busy with each keyframe, in sequence time, for the runners that
do not play frames on a camera's clock (the sequential runner; the threaded runner as fast as possible): monocular
tracking makes no keyframe while it is busy, as ORB-SLAM's in real time (docs/runtime.md)."""

from __future__ import annotations

from dataclasses import dataclass

from slamkit.errors import ConfigError
from slamkit.pipeline.outcomes import MappingState


@dataclass
class ModelledMapping:
    """A deterministic model of a busy local mapping thread (``runner.modelled_mapping_ms``).

    The sequential runner maps every keyframe to completion before the next frame, so local mapping is always idle
    when a frame is tracked and ORB-SLAM's keyframe condition c1b ("local mapping is idle", mMinFrames = 0) holds at
    every frame; the threaded runner playing a recorded sequence as fast as possible waits for local mapping before
    each keyframe it wants (``MappingState.waits_for_idle``), with the same effect. A real camera does not wait: ORB-SLAM2/3's local mapping takes about 100-300 ms per keyframe, and
    its monocular tracking makes no keyframe while it is busy (Tracking::NeedNewKeyFrame: ``!bLocalMappingIdle`` ->
    InterruptBA, monocular returns false). This model gives tracking that state without any clock: each keyframe
    made at a frame of timestamp t (s) keeps local mapping busy for ``busy_s`` of sequence time, queued behind the
    keyframes before it (a new map's two keyframes: twice as long), and a frame is tracked with
    ``MappingState(idle=False)`` while its timestamp is before the end of that work. Timestamps, not frame counts:
    KITTI's 10 Hz and TUM's 30 Hz frames see the same mapping time as a camera would.

    busy_s: modelled local mapping time per keyframe, s (0: local mapping always idle, the runner's behaviour
    without the model). new_map_busy_s: the time of each of the keyframes a new map is created with (None: busy_s).
    ORB-SLAM2/3's local mapping runs no local BA while the map holds at most two keyframes (LocalMapping::Run:
    ``KeyFramesInMap() > 2``) and triangulates and fuses them against one neighbour, so they take a few ms where a
    keyframe of a grown map takes 100-300 ms (ORB-SLAM3 on fr1_xyz makes a keyframe at the frame after its
    initialisation, 0.20 s after 0.17 s). Each cost is a constant, whatever the keyframe's local window, so the model
    stays a function of the timestamps alone.
    """

    busy_s: float = 0.0
    new_map_busy_s: float | None = None
    #: sequence time local mapping finishes the keyframes made so far, integer us (None: idle since the start)
    busy_until_us: int | None = None

    @property
    def busy_until_s(self) -> float | None:
        """Sequence time local mapping finishes the keyframes made so far, s (None: nothing made yet)."""
        return None if self.busy_until_us is None else self.busy_until_us / 1e6

    @property
    def enabled(self) -> bool:
        """Whether any keyframe is modelled to keep local mapping busy (a time > 0)."""
        return self.busy_s > 0.0 or (self.new_map_busy_s or 0.0) > 0.0

    def state(self, timestamp_s: float) -> MappingState:
        """Local mapping's state for a frame captured at ``timestamp_s`` (s): busy while the modelled work of the
        keyframes made so far is not done (``timestamp_s < busy_until_s``), compared in integer microseconds, so a
        frame captured exactly at the end (a 30 Hz camera's third frame after a keyframe with a 100 ms model) sees
        local mapping idle whether its timestamp came as a float sum (the synthetic room's i/30 s), as integer ns (a
        ROS bag's header stamp) or as an epoch time in s with six decimals (TUM's, whose float64 spacing near 1.3e9 s
        is 2.4e-7 s: a float or ns comparison there is decided by rounding)."""
        busy = self.busy_until_us is not None and _us(timestamp_s) < self.busy_until_us
        return MappingState(idle=not busy, accepting_keyframes=True)

    def keyframes_made(self, timestamp_s: float, n: int, new_map: bool = False) -> None:
        """``n`` keyframes were made at the frame captured at ``timestamp_s`` (s) (new_map: the keyframes a new map
        was created with): local mapping works on them one after the other, starting when it is done with the
        earlier ones."""
        each = self.new_map_busy_s if new_map and self.new_map_busy_s is not None else self.busy_s
        if n <= 0 or each <= 0.0:
            return
        t_us = _us(timestamp_s)
        start = t_us if self.busy_until_us is None else max(self.busy_until_us, t_us)
        self.busy_until_us = start + n * _us(each)

    def reset(self) -> None:
        """The map was reset or a new map started: local mapping's queue is emptied (ORB-SLAM RequestReset)."""
        self.busy_until_us = None


def _us(t_s: float) -> int:
    """A time in s as integer microseconds, rounded to the nearest: TUM's timestamp resolution, coarser than float64's
    rounding of an epoch time (< 0.25 us up to 2^31 s) and than a ROS stamp's ns."""
    return round(t_s * 1e6)


def modelled_mapping(modelled_mapping_ms: float, modelled_mapping_new_map_ms: float | None) -> ModelledMapping:
    """The model for ``runner.modelled_mapping_ms`` / ``runner.modelled_mapping_new_map_ms`` (ms; the latter None:
    the former), checked: ConfigError naming the key unless each is a time >= 0."""
    for key, ms in (
        ("modelled_mapping_ms", modelled_mapping_ms),
        ("modelled_mapping_new_map_ms", modelled_mapping_new_map_ms),
    ):
        if ms is not None and not ms >= 0.0:
            raise ConfigError(f"runner.{key} = {ms!r}: expected a time >= 0 (ms)")
    new_map_s = None if modelled_mapping_new_map_ms is None else modelled_mapping_new_map_ms / 1e3
    return ModelledMapping(modelled_mapping_ms / 1e3, new_map_s)
