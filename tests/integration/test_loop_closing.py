"""Loop closing acceptance (issue 5), on the synthetic world with the sequential runner. Slow: each run renders
and tracks a few thousand frames."""

from __future__ import annotations

from typing import Any

import pytest

from slamkit.app import build_runner
from slamkit.config import compose_config
from slamkit.eval.run_metrics import runner_metrics
from slamkit.pipeline.outcomes import LoopOutcome


def run_with_loops(*overrides: str) -> tuple[dict[str, Any], list[LoopOutcome]]:
    """Run with the sequential runner (bit-for-bit reproducible; the threaded one decides keyframes by timing)."""
    cfg = compose_config(["runner=sequential", "runner.progress=false", *overrides])
    runner, dataset = build_runner(cfg)
    runner.run(dataset, dataset.camera)
    metrics = runner_metrics(runner, dataset)
    return metrics, runner.log.loops


def run(*overrides: str) -> dict[str, Any]:
    return run_with_loops(*overrides)[0]


@pytest.mark.slow
@pytest.mark.timeout(4 * 3600)  # two runs of 2400 frames: ~40 min on an idle machine, hours on a shared one
def test_closing_the_long_loop_at_least_halves_the_keyframe_ate() -> None:
    closed = run("dataset.scene=long_loop")
    open_ = run("dataset.scene=long_loop", "pipeline.loop_closing.enabled=false")
    assert closed["loops_closed"] >= 1 and closed["loops_false"] == 0
    assert open_["loops_closed"] == 0
    assert closed["kf_ate_rmse_m"] <= 0.5 * open_["kf_ate_rmse_m"]


@pytest.mark.slow
@pytest.mark.timeout(3 * 3600)  # 2760 frames: ~10 min on an idle machine, much more on a shared one
def test_twin_places_give_no_false_loop() -> None:
    """Two places share repeated texture: only the true revisit (the camera passing its start) may close. The
    twin wall does fool place recognition and the Sim3 (a hypothesis reaches the geometric verification and is
    rejected there, with its reason recorded), so the test exercises the verification, not a quiet run.

    92 s instead of the scene's 86 s: the map initialises only ~7 s into the lap (frame ~219), so in 86 s the
    camera stops 0.8 m short of the map's first keyframe and sees its place in the last few frames only; 6 s
    more (same path, it repeats every 80 s) take it past the start again."""
    metrics, loops = run_with_loops("dataset.scene=twins", "dataset.duration_s=92")
    assert metrics["loops_false"] == 0
    assert metrics["loops_closed"] == 1
    rejected = [
        t
        for lp in loops
        for t in lp.tried
        if str(t.get("rejected", "")).startswith("verification") and lp.loop_kf_id is None
    ]
    assert rejected, "no loop hypothesis reached the geometric verification"
    # each records the turn it implies; the twin's imply a half turn (the corridor ring's symmetry)
    turns = [float(t["correction_rotation_deg"]) for t in rejected]  # type: ignore[arg-type]
    assert max(turns) > 150.0
