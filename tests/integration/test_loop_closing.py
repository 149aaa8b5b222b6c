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


def run_with_loops_in(runner: str, *overrides: str) -> tuple[dict[str, Any], list[LoopOutcome]]:
    """Like :func:`run_with_loops` with the given runner (``threaded`` is not reproducible bit for bit)."""
    cfg = compose_config([f"runner={runner}", "runner.progress=false", *overrides])
    built, dataset = build_runner(cfg)
    built.run(dataset, dataset.camera)
    return runner_metrics(built, dataset), built.log.loops


@pytest.mark.slow
@pytest.mark.timeout(3 * 3600)  # 2760 frames: ~10 min on an idle machine, much more on a shared one
@pytest.mark.parametrize("runner", ["sequential", "threaded"])
@pytest.mark.parametrize(
    "scene",
    ["twins", "twins_translated"],
)
def test_twin_places_give_no_false_loop(scene: str, runner: str) -> None:
    """Two places share repeated texture: only the true revisit (the camera passing its start) may close. In
    ``twins`` the twin places are related by a half turn (the corridor ring's symmetry), in ``twins_translated``
    by a 12 m translation along one wall (a rotation prior cannot tell it). The twin wall does fool place
    recognition, so a hypothesis is examined and rejected by geometry (the Sim3 and guided matching over the
    candidate's covisible window) or consistency (the next keyframes), with its reason recorded.

    In ``twins_translated`` crates stand in different places in front of the two twin panels: a twin that fills
    the view exactly as at its twin place (the scene's first version) is a revisit to every check on the views,
    ORB-SLAM3's included (it closed 742 <-> 11 with 91 refined matches, 3 covisibles agreeing), not a false loop
    a SLAM system can reject; a real twin differs in some structure in view, which the verification sees.

    92 s instead of the scenes' 86 s: the map initialises only ~7 s into the lap (frame ~219), so in 86 s the
    camera stops 0.8 m short of the map's first keyframe and sees its place in the last few frames only; 6 s
    more (same path, it repeats every 80 s) take it past the start again."""
    metrics, loops = run_with_loops_in(runner, f"dataset.scene={scene}", "dataset.duration_s=92")
    assert metrics["loops_false"] == 0
    assert metrics["loops_closed"] == 1
    rejected = [t for lp in loops for t in lp.tried if t.get("rejected") and lp.loop_kf_id is None]
    assert rejected, "no loop hypothesis was examined and rejected"


@pytest.mark.slow
@pytest.mark.timeout(2 * 3600)  # 840 frames: ~3 min on an idle machine
@pytest.mark.parametrize("runner", ["sequential", "threaded"])
def test_the_global_ba_after_the_room_loop_completes_and_keeps_the_map_accurate(runner: str) -> None:
    """ORB-SLAM2's global BA after the loop: in line (sequential) or in its own thread (threaded), written back
    with what was added meanwhile corrected; the room's keyframe ATE stays within 2 cm (1.2-1.4 cm without it)."""
    cfg = compose_config([f"runner={runner}", "runner.progress=false", "pipeline.loop_closing.global_ba=true"])
    built, dataset = build_runner(cfg)
    built.run(dataset, dataset.camera)
    metrics = runner_metrics(built, dataset)
    assert metrics["loops_closed"] == 1 and metrics["loops_false"] == 0
    assert built.loop_closer is not None
    assert [g.aborted for g in built.loop_closer.global_bas] == [False]
    assert built.loop_closer.global_bas[0].keyframes > 50
    if runner == "sequential":
        assert built.loop_closer.global_bas[0].propagated_keyframes == 0  # nothing runs beside it
    assert metrics["kf_ate_rmse_m"] < 0.02
