"""The report's PNG and ``slamkit report`` on a partially finished sweep directory."""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import pytest

from slamkit.cli import main
from slamkit.report.aggregate import aggregate
from slamkit.report.collect import JobResult, Sweep
from slamkit.report.plots import plot_report

from .conftest import WriteJob, WriteMultirun, ok_metrics

THETA = "pipeline.loop_closing.theta_min"


def _sweep(values: list[str], key: str = THETA) -> Sweep:
    jobs = [
        JobResult(
            {key: v, "seed": str(s)}, "ok", {"kf_ate_rmse_m": 0.01 + 0.001 * s, "essential_graph_ms_total": 100.0}
        )
        for v in values
        for s in range(2)
    ]
    return Sweep(Path("."), jobs)


@pytest.mark.parametrize("values", [["15", "50", "100", "200"], ["true", "false"]])
def test_plot_has_a_panel_per_metric_with_values(tmp_path: Path, values: list[str]) -> None:
    path = tmp_path / "img" / "sweep.png"
    panels = plot_report(aggregate(_sweep(values)), path, title="t")
    assert panels == ["kf_ate_rmse_m", "essential_graph_ms_total"]
    image = cv2.imread(str(path))
    assert image is not None and image.shape[1] > image.shape[0] > 200  # two panels side by side, one row


def test_no_metric_no_plot(tmp_path: Path) -> None:
    sweep = Sweep(Path("."), [JobResult({"x": "1"}, "failed", {}, "boom")])
    assert plot_report(aggregate(sweep), tmp_path / "p.png") == []
    assert not (tmp_path / "p.png").exists()


def test_report_command_on_a_sweep_still_running(
    tmp_path: Path,
    job_writer: WriteJob,
    multirun_writer: WriteMultirun,
    capsys: pytest.CaptureFixture[str],
) -> None:
    root = tmp_path / "multirun"
    multirun_writer(root, ["+sweep=theta_min", "hydra.sweeper.params.seed='0,1'"])
    base = ["+sweep=theta_min"]
    job_writer(root, 0, [f"{THETA}=15", "seed=0", *base], ok_metrics(0, essential_graph_edges_max=3000))
    job_writer(root, 1, [f"{THETA}=15", "seed=1", *base], ok_metrics(1, essential_graph_edges_max=3100))
    job_writer(root, 2, [f"{THETA}=50", "seed=0", *base], {"status": "failed", "error": "ConfigError: bad"})
    job_writer(root, 3, [f"{THETA}=50", "seed=1", *base], None)
    out_csv = tmp_path / "table.csv"
    assert main(["report", str(root), "--csv", str(out_csv)]) == 0
    text = capsys.readouterr().out
    assert "3050 [3000, 3100]" in text
    assert "ok 0/2, failed 1, incomplete 1" in text
    assert "ok 0/2, pending 2" in text  # theta_min 100 and 200 not started
    assert "theta_min=50 seed=0: ConfigError: bad" in text
    rows = list(csv.DictReader(out_csv.open()))
    assert [r[THETA] for r in rows] == ["15", "50", "100", "200"]
    assert "| 15 | ok 2/2 | 3050 [3000, 3100] |" in (root / "report.md").read_text()
    assert cv2.imread(str(root / "report.png")) is not None


def test_report_command_names_a_missing_directory(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["report", str(tmp_path / "nope")]) == 2
    assert f"slamkit report: {tmp_path / 'nope'}: no such multirun directory" in capsys.readouterr().err
