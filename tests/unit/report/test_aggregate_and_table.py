"""Aggregation over seeds (median, min, max), setting order, failed jobs, and the three renderings of the table."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import pytest

from slamkit.report.aggregate import Stat, aggregate
from slamkit.report.collect import JobResult, Sweep
from slamkit.report.table import format_stat, render_csv, render_markdown, render_text, short_key

THETA = "pipeline.loop_closing.theta_min"


def job(theta: str, seed: int, status: str = "ok", error: str | None = None, **metrics: object) -> JobResult:
    overrides = {THETA: theta, "seed": str(seed), "sweep": "theta_min"}
    return JobResult(overrides, status, {"status": status, **metrics} if status != "pending" else {}, error)


@pytest.fixture
def sweep() -> Sweep:
    return Sweep(
        Path("multirun/x"),
        [
            job("100", 0, essential_graph_edges_max=900, essential_graph_ms_total=410.0, kf_ate_rmse_m=0.012),
            job("100", 1, essential_graph_edges_max=950, essential_graph_ms_total=390.0, kf_ate_rmse_m=0.010),
            job("100", 2, essential_graph_edges_max=1000, essential_graph_ms_total=500.0, kf_ate_rmse_m=0.020),
            job("15", 0, essential_graph_edges_max=3000, essential_graph_ms_total=900.0, kf_ate_rmse_m=0.011),
            job("15", 1, "failed", "DatasetError: /data/x: no such file\nsecond line"),
            job("15", 2, "pending"),
            # an older run: only the per-loop lists, two loops
            job("50", 0, essential_graph_edges=[1500, 2000], essential_graph_ms=[300.0, 400.0], kf_ate_rmse_m=0.01),
        ],
    )


def test_rows_are_settings_in_numeric_order_with_median_min_max_over_seeds(sweep: Sweep) -> None:
    report = aggregate(sweep)
    assert report.keys == [THETA]  # seed and the constant +sweep are not part of a setting
    assert [r.setting[THETA] for r in report.rows] == ["15", "50", "100"]
    r15, r50, r100 = report.rows
    assert r100.stats["essential_graph_edges_max"] == Stat(950.0, 900.0, 1000.0, 3)
    assert r100.stats["essential_graph_ms_total"] == Stat(410.0, 390.0, 500.0, 3)
    assert r15.stats["essential_graph_edges_max"] == Stat(3000.0, 3000.0, 3000.0, 1)  # failed/pending left out
    assert (r15.count("ok"), r15.count("failed"), r15.count("pending"), r15.status) == (
        1,
        1,
        1,
        "ok 1/3, failed 1, pending 1",
    )
    assert r15.errors() == [("1", "DatasetError: /data/x: no such file\nsecond line")]
    # summaries derived from the lists when the scalar keys are absent: largest graph, total time
    assert r50.stats["essential_graph_edges_max"] == Stat(2000.0, 2000.0, 2000.0, 1)
    assert r50.stats["essential_graph_ms_total"] == Stat(700.0, 700.0, 700.0, 1)
    assert r50.stats["keyframes"] is None


def test_non_numbers_are_not_aggregated() -> None:
    report = aggregate(
        Sweep(Path("."), [job("1", 0, keyframes=float("nan")), JobResult({"seed": "1"}, "ok", {"keyframes": True})])
    )
    assert all(r.stats["keyframes"] is None for r in report.rows)


def test_stat_formatting_and_short_keys() -> None:
    assert format_stat(Stat(0.5, 0.25, 1.0, 3), "%.2f") == "0.50 [0.25, 1.00]"
    assert format_stat(Stat(3.0, 3.0, 3.0, 2), "%.0f") == "3"
    assert format_stat(None, "%.0f") == "-"
    assert short_key(THETA, [THETA, "seed"]) == "theta_min"
    assert short_key("a.x", ["a.x", "b.x"]) == "a.x"


def test_text_table_aligns_rows_and_lists_failed_jobs(sweep: Sweep) -> None:
    text = render_text(aggregate(sweep))
    lines = text.splitlines()
    assert lines[0].split()[:5] == ["theta_min", "jobs", "KF", "ATE", "m"]
    assert "ATE m" in lines[0] and "EG edges" in lines[0] and "KFs" not in lines[0]  # no run has keyframes
    assert lines[2].startswith("15 ") and "ok 1/3, failed 1, pending 1" in lines[2]
    assert "950 [900, 1000]" in lines[4] and "410 [390, 500]" in lines[4]
    assert len({len(line) for line in lines[:2]}) == 1
    assert "failed jobs:" in lines
    assert "  theta_min=15 seed=1: DatasetError: /data/x: no such file" in lines


def test_markdown_table(sweep: Sweep) -> None:
    md = render_markdown(aggregate(sweep)).splitlines()
    assert md[0] == "| theta_min | jobs | KF ATE m | EG edges | EG ms |"
    assert md[1] == "| --- | --- | ---: | ---: | ---: |"
    assert md[4] == "| 100 | ok 3/3 | 0.0120 [0.0100, 0.0200] | 950 [900, 1000] | 410 [390, 500] |"
    assert md[-1] == "- `theta_min=15 seed=1: DatasetError: /data/x: no such file`"


def test_csv_has_one_column_per_statistic_and_the_errors(sweep: Sweep) -> None:
    rows = list(csv.DictReader(io.StringIO(render_csv(aggregate(sweep)))))
    assert [r[THETA] for r in rows] == ["15", "50", "100"]
    r15, _, r100 = rows
    assert (r100["essential_graph_edges_max_median"], r100["essential_graph_edges_max_min"]) == ("950.0", "900.0")
    assert (r100["essential_graph_edges_max_max"], r100["essential_graph_edges_max_n"]) == ("1000.0", "3")
    assert (r15["jobs"], r15["jobs_ok"], r15["jobs_failed"], r15["jobs_pending"]) == ("3", "1", "1", "1")
    assert r15["errors"] == "seed=1: DatasetError: /data/x: no such file"
    assert (r15["keyframes_median"], r15["keyframes_n"]) == ("", "0")
