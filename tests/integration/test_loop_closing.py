"""Loop closing acceptance (issue 5), on the synthetic world with the sequential runner. Slow: each run renders
and tracks a few thousand frames."""

from __future__ import annotations

from typing import Any

import pytest

from slamkit.app import build_runner, run_metrics
from slamkit.config import compose_config


def run(*overrides: str) -> dict[str, Any]:
    cfg = compose_config(["runner.progress=false", *overrides])
    runner, dataset = build_runner(cfg)
    runner.run(dataset, dataset.camera)
    return run_metrics(
        runner.log, runner.store, runner.recorder.frames(runner.store), runner.recorder.keyframes(runner.store), dataset
    )


@pytest.mark.slow
def test_closing_the_long_loop_at_least_halves_the_keyframe_ate() -> None:
    closed = run("dataset.scene=long_loop")
    open_ = run("dataset.scene=long_loop", "pipeline.loop_closing.enabled=false")
    assert closed["loops_closed"] >= 1 and closed["loops_false"] == 0
    assert open_["loops_closed"] == 0
    assert closed["kf_ate_rmse_m"] <= 0.5 * open_["kf_ate_rmse_m"]


@pytest.mark.slow
def test_twin_places_give_no_false_loop() -> None:
    """Two places share repeated texture: only the true revisit (the camera passing its start) may close."""
    metrics = run("dataset.scene=twins")
    assert metrics["loops_false"] == 0
    assert metrics["loops_closed"] == 1
