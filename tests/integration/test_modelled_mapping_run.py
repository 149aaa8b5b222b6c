"""The sequential runner with a modelled busy local mapping (``runner.modelled_mapping_ms``) on the synthetic room:
a monocular run makes no keyframe from a frame captured within the modelled time of the last keyframe and makes
them after; stereo frames always see local mapping idle (their keyframes are unchanged)."""

from __future__ import annotations

import itertools
from typing import Any

import pytest

from slamkit.app import build_runner
from slamkit.config import compose_config
from slamkit.pipeline.outcomes import KeyFrameDecision, MappingState, TrackingOutcome
from slamkit.runtime.sequential import SequentialRunner

pytestmark = pytest.mark.timeout(300)


def _run(overrides: list[str]) -> list[tuple[MappingState, TrackingOutcome]]:
    """Run the room with ``overrides``; each frame's local mapping state as tracking got it, and the outcome."""
    cfg = compose_config(["runner=sequential", "runner.progress=false", "dataset.depth=false", *overrides])
    runner, dataset = build_runner(cfg)
    assert isinstance(runner, SequentialRunner)
    seen: list[tuple[MappingState, TrackingOutcome]] = []
    step = runner.tracker.step

    def recording_step(data: Any, camera: Any, mapping: MappingState) -> TrackingOutcome:
        out = step(data, camera, mapping)
        seen.append((mapping, out))
        return out

    runner.tracker.step = recording_step  # type: ignore[method-assign,assignment]
    runner.run(dataset, dataset.camera)
    return seen


def test_monocular_keyframes_wait_for_the_modelled_local_mapping() -> None:
    busy_s = 0.2
    seen = _run(
        [
            "dataset.max_frames=45",
            f"runner.modelled_mapping_ms={busy_s * 1e3:g}",
            "runner.modelled_mapping_new_map_ms=null",
        ]
    )
    made = [(m, o) for m, o in seen if o.keyframe_ids]
    assert made[0][1].initialized_map and len(made) >= 3
    # no keyframe from a frame that saw local mapping busy; each one made after the modelled time of the last
    assert all(m.idle for m, _ in made)
    busy_frames = [o for m, o in seen if not m.idle]
    assert busy_frames and all(o.keyframe != KeyFrameDecision.INSERT for o in busy_frames)
    for (_, prev), (_, cur) in itertools.pairwise(made):
        n_prev = len(prev.keyframe_ids)  # a new map's two keyframes keep local mapping busy twice as long
        assert cur.timestamp_s >= prev.timestamp_s + n_prev * busy_s - 1e-9
    # and a frame tracked busy came right after a keyframe: within its modelled time
    for o in busy_frames:
        last = [p for _, p in made if p.timestamp_s < o.timestamp_s][-1]
        assert o.timestamp_s < last.timestamp_s + len(last.keyframe_ids) * busy_s
    # the model keeps monocular keyframes that c2 alone would make every few frames apart
    without = _run(["dataset.max_frames=45", "runner.modelled_mapping_ms=0"])
    assert all(m.idle for m, _ in without)
    assert len(made) < sum(bool(o.keyframe_ids) for _, o in without)


def test_stereo_frames_always_see_local_mapping_idle() -> None:
    seen = _run(["frontend=stereo", "dataset.stereo=true", "dataset.max_frames=12", "runner.modelled_mapping_ms=300"])
    # the stereo map starts with one keyframe at the first frame; the next 11 frames (0.37 s at 30 Hz) are within the
    # modelled 300 ms of it or of a keyframe after it, and all see local mapping idle
    assert len(seen) == 12 and seen[0][1].keyframe_ids
    assert all(m.idle for m, _ in seen)
