"""RGB-D and stereo ORB-SLAM (frontend=rgbd, frontend=stereo) end to end on the synthetic room (sequential runner): it initialises from the
first frame, tracks every frame, and its trajectory is metric (ATE after an SE(3) alignment, no scale); monocular
runs are untouched by the stereo code paths."""

from __future__ import annotations

import numpy as np
import pytest

from slamkit.app import build_runner
from slamkit.config import compose_config
from slamkit.eval.metrics import compute_ate
from slamkit.eval.run_metrics import runner_metrics
from slamkit.pipeline.tracking import TrackingState

BASE = ["runner=sequential", "runner.progress=false", "optimizer.worker=inline"]
RGBD = ["frontend=rgbd"]
STEREO = ["frontend=stereo", "dataset.stereo=true"]


def run(*overrides: str) -> tuple[dict, object, object]:
    cfg = compose_config([*BASE, *overrides])
    runner, dataset = build_runner(cfg)
    runner.run(dataset, dataset.camera)
    return runner_metrics(runner, dataset), runner, dataset


def _check_metric(metrics: dict, runner: object, dataset: object, ate_se3_m: float) -> None:
    states = [o.state for o in runner.log.tracking]  # type: ignore[attr-defined]
    assert metrics["initialized_at_frame"] == 0, "RGB-D initialises from the first frame"
    assert all(s == TrackingState.OK for s in states), "every frame tracked"
    # one pose per frame: the first keyframe is the first frame itself (no separate reference frame)
    frames = runner.recorder.frames(runner.store)  # type: ignore[attr-defined]
    assert len(frames) == len(states) and len(np.unique(frames.t_s)) == len(states)
    assert metrics["ate_se3_rmse_m"] < ate_se3_m
    # metric scale: the Sim(3) alignment finds a scale within 0.5% of 1
    ate = compute_ate(dataset.ground_truth, frames, align="sim3", max_diff_s=0.01)  # type: ignore[attr-defined]
    assert abs(ate.scale - 1.0) < 0.005


#: ORB-SLAM2's right-coordinate gates (SearchByProjection, Fuse), off by default (docs/pipeline.md)
GATES = ["pipeline.tracking.right_coordinate_gate=true", "pipeline.local_mapping.fuse_right_coordinate_gate=true"]


@pytest.mark.parametrize("sensor", [RGBD, STEREO, RGBD + GATES], ids=["rgbd", "stereo", "rgbd-gates"])
def test_room_start_is_tracked_with_metric_scale(sensor: list[str]) -> None:
    metrics, runner, dataset = run(*sensor, "dataset.max_frames=45")
    assert metrics["keyframes"] >= 2
    _check_metric(metrics, runner, dataset, 0.01)


@pytest.mark.slow
@pytest.mark.parametrize(
    "seed",
    [
        0,
        1,
        pytest.param(
            2, marks=pytest.mark.xfail(reason="issue 16: seed 2 measured 1.16 cm (> 1 cm), open", strict=False)
        ),
    ],
)
def test_room_whole_loop_stereo(seed: int) -> None:
    """The whole room (840 frames, one loop) with the 0.12 m stereo pair: every frame, under 1 cm, the loop closed."""
    metrics, runner, dataset = run(*STEREO, f"seed={seed}")
    _check_metric(metrics, runner, dataset, 0.01)
    assert metrics["loops_closed"] >= 1 and metrics["loops_false"] == 0


@pytest.mark.slow
@pytest.mark.xfail(reason="issue 16: RGB-D drifts in the room's fast turn (frames 200-250): 2.7 cm, open", strict=False)
def test_room_whole_loop_rgbd() -> None:
    metrics, runner, dataset = run(*RGBD, "seed=0")
    _check_metric(metrics, runner, dataset, 0.01)
    assert metrics["loops_closed"] >= 1 and metrics["loops_false"] == 0
