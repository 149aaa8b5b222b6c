"""Kidnapping (issue 5): the camera jumps (a span of frames skipped) to a place already mapped; tracking is
lost, relocalizes within 5 frames and continues, with relocalized poses close to the truth."""

from __future__ import annotations

import numpy as np
import pytest

from slamkit.app import build_runner
from slamkit.config import compose_config
from slamkit.eval.metrics import compute_ate
from slamkit.pipeline.tracking import TrackingState


def test_kidnapped_camera_relocalizes_within_five_frames() -> None:
    # the room's trajectory returns to its start: frames 791.. see what frames 0..149 mapped
    cfg = compose_config(
        ["runner=sequential", "runner.progress=false", "dataset.skip=[150,790]", "pipeline.loop_closing.enabled=false"]
    )
    runner, dataset = build_runner(cfg)
    runner.run(dataset, dataset.camera)
    outcomes = runner.log.tracking
    jump = next(i for i, o in enumerate(outcomes) if o.frame_index == 150)  # first frame after the skipped span
    assert all(o.state == TrackingState.OK for o in outcomes[jump - 20 : jump]), "tracked before the jump"
    after = [o.state for o in outcomes[jump:]]
    assert after[0] == TrackingState.LOST, "the jump must lose the track"
    first_ok = after.index(TrackingState.OK)
    assert first_ok <= 5, f"relocalized only after {first_ok} frames"
    assert outcomes[jump + first_ok].method == "relocalization"
    assert all(s == TrackingState.OK for s in after[first_ok:]), "tracking continues after relocalizing"
    # accuracy of the whole trajectory, relocalized part included: within 2% of the scene's scale
    gt = dataset.ground_truth
    assert gt is not None
    ate = compute_ate(gt, runner.recorder.frames(runner.store), align="sim3")
    scene_scale = float(np.linalg.norm(np.ptp(gt.positions_m, axis=0)))
    relocated = ate.errors_m[ate.t_s >= outcomes[jump + first_ok].timestamp_s - 1e-6]
    assert relocated.size >= 40
    assert relocated.max() < 0.02 * scene_scale


@pytest.mark.slow  # a 310-frame run; the default suite keeps the kidnapping test above (issue: suite under 10 min)
def test_relocalization_thresholds_are_read_from_the_config() -> None:
    """The same jump with V-C's BoW-match threshold swept out of reach: no candidate is tried, tracking stays lost
    (with the default 15 it relocalizes within 5 frames, above)."""
    cfg = compose_config(
        [
            "runner=sequential",
            "runner.progress=false",
            "dataset.skip=[300,790]",
            "dataset.max_frames=310",  # 300 frames before the jump, 10 after
            "pipeline.loop_closing.enabled=false",
            "pipeline.tracking.reloc_min_bow_matches=100000",
        ]
    )
    runner, dataset = build_runner(cfg)
    runner.run(dataset, dataset.camera)
    outcomes = runner.log.tracking
    jump = next(i for i, o in enumerate(outcomes) if o.frame_index == 300)
    assert outcomes[jump - 1].state == TrackingState.OK
    assert len(outcomes) - jump == 10
    assert all(o.state == TrackingState.LOST and o.method == "relocalization" for o in outcomes[jump + 1 :])
