"""The scalar loop summaries every job writes into metrics.json (what a sweep report aggregates)."""

from __future__ import annotations

from slamkit.eval.run_metrics import loop_summaries
from slamkit.pipeline.outcomes import LoopOutcome
from slamkit.runtime.log import RunLog


def test_summaries_cover_closed_loops_only() -> None:
    run = RunLog()
    run.loops.append(LoopOutcome(5, candidates=[1], reason="no candidate passed the Sim3 checks"))
    run.loops.append(
        LoopOutcome(
            40,
            loop_kf_id=2,
            essential_graph_edges=900,
            timings_ms={"essential_graph_ms": 120.0, "correction_ms": 300.0},
        )
    )
    run.loops.append(
        LoopOutcome(
            90,
            loop_kf_id=7,
            essential_graph_edges=1400,
            timings_ms={"essential_graph_ms": 200.5, "correction_ms": 450.0},
        )
    )
    assert loop_summaries(run) == {
        "essential_graph_edges_max": 1400,
        "essential_graph_ms_total": 320.5,
        "loop_correction_ms_total": 750.0,
    }


def test_no_loop_no_summary() -> None:
    run = RunLog()
    run.loops.append(LoopOutcome(5, candidates=[1]))
    assert loop_summaries(run) == {
        "essential_graph_edges_max": None,
        "essential_graph_ms_total": None,
        "loop_correction_ms_total": None,
    }
