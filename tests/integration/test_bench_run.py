"""`slamkit bench`: a real run, stage timings, the JSON keys issue 6 names, and the side-by-side comparison."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from slamkit.cli import main

pytestmark = pytest.mark.timeout(600)


def test_bench_runs_both_runners_side_by_side_and_writes_the_json(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "bench.json"
    rc = main(
        ["bench", "--no-progress", "--runners", "threaded,sequential", "--json", str(out), "dataset.max_frames=60"]
    )
    assert rc == 0
    result = json.loads(out.read_text())
    for key in ("tracking_ms_median", "local_mapping_ms_median", "frames_dropped", "realtime_factor", "peak_rss_mb"):
        assert key in result, key
    runs = {r["runner"]: r for r in result["runs"]}
    assert set(runs) == {"threaded", "sequential"}
    for run in runs.values():
        assert run["status"] == "ok" and run["frames"] == 60
        tracking = run["stages"]["tracking"]
        # every tracked frame after initialisation has each stage timed, and the stages fit in the whole
        n = tracking["track_ms"]["n"]
        assert n >= 40
        assert all(tracking[s]["n"] == n for s in ("extract_ms", "initial_pose_ms", "local_map_ms"))
        assert tracking["extract_ms"]["median"] < tracking["track_ms"]["median"]
        assert run["stages"]["local_mapping"]["local_ba_ms"]["n"] >= 1
        assert run["peak_rss_mb"] > 50 and run["frames_dropped"] == 0
        assert run["ate_rmse_m"] < 0.05
    assert result["ate_ratio_threaded_over_sequential"] == pytest.approx(
        runs["threaded"]["ate_rmse_m"] / runs["sequential"]["ate_rmse_m"]
    )
    table = capsys.readouterr().out
    assert "tracking.extract_ms" in table and "local_mapping.local_ba_ms" in table and "threaded median / p95" in table


def test_bench_reports_a_bad_override_clearly(capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["bench", "--no-progress", "runner.kind=turbo", "dataset.max_frames=5"])
    assert rc == 2
    assert "runner.kind = 'turbo'" in capsys.readouterr().err


def test_bench_composes_every_runners_config_before_running_any(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """runner.preload exists for the threaded runner only: the sequential run cannot be composed, and the bench
    says so before spending time on the threaded run (whose figures it would otherwise lose)."""
    out = tmp_path / "bench.json"
    rc = main(["bench", "--no-progress", "--runners", "threaded,sequential", "--json", str(out), "runner.preload=true"])
    assert rc == 2 and not out.exists()
    err = capsys.readouterr().err
    assert "cannot compose the config for runner.preload=true runner=sequential" in err
    assert "runner.preload" in err and "Traceback" not in err
