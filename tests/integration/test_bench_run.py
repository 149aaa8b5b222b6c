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
        [
            "bench",
            "--no-progress",
            "--runners",
            "threaded,sequential",
            "--json",
            str(out),
            "--plot",
            str(tmp_path / "growth.png"),
            "dataset.max_frames=60",
        ]
    )
    assert rc == 0
    # the cost-against-map-size plot, one per runner (too short a run for the growth table: 200 frames are skipped)
    for kind in ("threaded", "sequential"):
        assert (tmp_path / f"growth_{kind}.png").read_bytes()[:4] == b"\x89PNG"
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
        # the frame's own work (the wait for local mapping taken out) is never more than its tracking time, and
        # without waits (sequential: local mapping runs in line, nothing waits) it is the tracking time itself
        assert tracking["work_ms"]["n"] == n
        assert run["tracking_work_ms_median"] <= run["tracking_ms_median"]
        if tracking["mapping_wait_ms"]["n"] == 0:
            assert run["tracking_work_ms_median"] == run["tracking_ms_median"]
        assert run["stages"]["local_mapping"]["local_ba_ms"]["n"] >= 1
        # played as fast as possible no local BA is skipped or stopped (the threaded runner waits for local mapping
        # rather than abort it); every keyframe but a map's first two is due one
        ba = run["local_ba_completed"]
        assert ba["due"] >= run["keyframes_inserted"] - 2 and ba["completed"] == ba["due"] and ba["fraction"] == 1.0
        assert run["peak_rss_mb"] > 50 and run["frames_dropped"] == 0
        assert run["ate_rmse_m"] < 0.05
    assert result["ate_ratio_threaded_over_sequential"] == pytest.approx(
        runs["threaded"]["ate_rmse_m"] / runs["sequential"]["ate_rmse_m"]
    )
    table = capsys.readouterr().out
    assert "tracking.extract_ms" in table and "local_mapping.local_ba_ms" in table and "threaded median / p95" in table
    assert "local BA completed / due (skipped, aborted)" in table


@pytest.mark.slow
def test_bench_reports_cost_against_map_size_after_the_first_200_frames(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The growth record of a 240-frame sequential run: four parts of 10 frames after the first 200, the map's
    keyframes counted at their ends (never fewer than local mapping left), and memory per keyframe."""
    out = tmp_path / "bench.json"
    rc = main(["bench", "--no-progress", "--json", str(out), "runner=sequential", "dataset.max_frames=240"])
    assert rc == 0
    run = json.loads(out.read_text())["runs"][0]
    growth = run["growth"]
    assert [p["frames"] for p in growth["parts"]] == [[200, 209], [210, 219], [220, 229], [230, 239]]
    assert growth["parts"][-1]["keyframes_at_end"] == run["keyframes"]
    assert sum(p["keyframes_mapped"] for p in growth["parts"]) >= 1
    assert all(p["tracked_frames"] == 10 and p["tracking_ms_median"] > 0 for p in growth["parts"])
    assert growth["rss_mb_per_keyframe"] is not None
    assert "cost as the map grows (after the first 200 frames)" in capsys.readouterr().out


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
