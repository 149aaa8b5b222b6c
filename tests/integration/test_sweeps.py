"""Sweeps through the command line: `slamkit run -m` runs the jobs two at a time (joblib launcher), a failing job
records its error and the others finish, any config value can be swept, `slamkit report` aggregates the result;
the slow tests run ORB-SLAM's theta_min study on the room scene and the same sweep on a local Ray instance."""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from datetime import datetime
from pathlib import Path

import pytest
import yaml

from slamkit.report.aggregate import aggregate
from slamkit.report.collect import collect_sweep

THETA = "pipeline.loop_closing.theta_min"
INIT = "pipeline.tracking.init_min_matches"
_LOG_TIME = re.compile(r"^\[(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3})\]")


def slamkit(*args: str, cwd: Path, timeout: float) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "slamkit", *args], cwd=cwd, capture_output=True, text=True, timeout=timeout
    )


def log_span(app_log: Path) -> tuple[datetime, datetime]:
    """First and last timestamps of a job's Hydra log (app.log)."""
    stamps = [m.group(1) for line in app_log.read_text().splitlines() if (m := _LOG_TIME.match(line))]
    first, last = (datetime.strptime(s, "%Y-%m-%d %H:%M:%S,%f") for s in (stamps[0], stamps[-1]))
    return first, last


def metrics_by_setting(root: Path, *keys: str) -> dict[tuple[str, ...], dict[str, object]]:
    return {tuple(j.overrides[k] for k in keys): j.metrics for j in collect_sweep(root).jobs}


def test_sweep_runs_two_jobs_at_a_time_records_a_failure_and_sweeps_any_value(tmp_path: Path) -> None:
    root = tmp_path / "multirun"
    result = slamkit(
        "run",
        "-m",
        "runner.progress=false",
        "dataset.max_frames=12",
        "dataset.scene=room,nowhere",  # a setting that cannot build its dataset (jobs 2 and 3)
        f"{INIT}=100,100000",  # an arbitrary tracking parameter: 100000 matches never initialise the map
        f"hydra.sweep.dir={root}",
        cwd=tmp_path,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "Joblib.Parallel(n_jobs=2," in result.stdout + result.stderr
    jobs = metrics_by_setting(root, INIT, "dataset.scene")
    assert len(jobs) == 4
    for init in ("100", "100000"):
        failed = jobs[(init, "nowhere")]
        assert failed["status"] == "failed" and failed["stage"] == "build"
        assert "ConfigError: dataset.scene: unknown synthetic scene 'nowhere'" in str(failed["error"])
    ok, never = jobs[("100", "room")], jobs[("100000", "room")]
    assert ok["status"] == never["status"] == "ok" and ok["frames"] == never["frames"] == 12
    assert ok["initialized_at_frame"] is not None and int(str(ok["frames_tracked"])) > 0
    assert never["initialized_at_frame"] is None and never["frames_tracked"] == 0
    for job in collect_sweep(root).jobs:  # each job's resolved config has its own value
        assert job.job_dir is not None
        config = yaml.safe_load((job.job_dir / "config.yaml").read_text())
        assert config["pipeline"]["tracking"]["init_min_matches"] == int(job.overrides[INIT])
    # jobs 0 and 1 (the two room runs) ran side by side
    (a0, a1), (b0, b1) = log_span(root / "0" / "app.log"), log_span(root / "1" / "app.log")
    assert a0 < b1 and b0 < a1

    report = slamkit("report", str(root), "--csv", str(tmp_path / "t.csv"), cwd=tmp_path, timeout=120)
    assert report.returncode == 0, report.stderr
    lines = report.stdout.splitlines()
    assert lines[0].split()[:3] == ["scene", "init_min_matches", "jobs"]
    rows = {tuple(line.split()[:2]): line for line in lines[2:6]}
    assert "ok 0/1, failed 1" in rows[("nowhere", "100")] and "ok 1/1" in rows[("room", "100000")]
    assert (
        "scene=nowhere init_min_matches=100000 seed=0: slamkit.errors.ConfigError: dataset.scene: unknown synthetic"
        in (report.stdout)
    )
    assert (root / "report.png").is_file() and (tmp_path / "t.csv").is_file()


@pytest.mark.slow
def test_theta_min_sweep_on_the_room_loop(tmp_path: Path) -> None:
    """ORB-SLAM Table VI on the room scene (one loop): fewer essential-graph edges as theta_min rises, and less
    time optimizing them. Four room runs, two at a time: about 6 min on an idle 2-core machine."""
    root = tmp_path / "multirun"
    result = slamkit(
        "run",
        "+sweep=theta_min",
        "seed=0",
        "runner.progress=false",
        f"hydra.sweep.dir={root}",
        cwd=tmp_path,
        timeout=5400,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    report = aggregate(collect_sweep(root))
    assert [r.setting[THETA] for r in report.rows] == ["15", "50", "100", "200"]
    assert all(r.status == "ok 1/1" for r in report.rows)
    edges = [r.stats["essential_graph_edges_max"] for r in report.rows]
    times = [r.stats["essential_graph_ms_total"] for r in report.rows]
    assert all(e is not None for e in edges) and all(t is not None for t in times), "a run closed no loop"
    medians = [e.median for e in edges if e is not None]
    assert medians == sorted(medians, reverse=True) and medians[0] > 1.5 * medians[-1]
    assert times[0] is not None and times[-1] is not None and times[0].median > times[-1].median
    text = slamkit("report", str(root), cwd=tmp_path, timeout=120)
    assert text.returncode == 0 and "EG edges" in text.stdout and "EG ms" in text.stdout


def _ray_missing() -> str | None:
    for module in ("ray", "hydra_plugins.hydra_ray_launcher"):
        try:
            if importlib.util.find_spec(module) is None:
                return module
        except ModuleNotFoundError:
            return module
    return None


@pytest.mark.slow
@pytest.mark.skipif(
    _ray_missing() is not None,
    reason=f"{_ray_missing()} is not importable: the Ray launcher is the optional extra (pip install '.[ray]')",
)
def test_the_same_sweep_runs_on_a_local_ray_instance(tmp_path: Path) -> None:
    root = tmp_path / "multirun"
    result = slamkit(
        "run",
        "+sweep=theta_min",
        "hydra/launcher=ray",
        "+hydra.launcher.ray.init.num_cpus=2",
        "+hydra.launcher.ray.init.include_dashboard=false",
        "seed=0",
        "dataset.max_frames=12",
        "runner.progress=false",
        f"hydra.sweep.dir={root}",
        cwd=tmp_path,
        timeout=900,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "Ray Launcher is launching 4 jobs" in result.stdout + result.stderr
    jobs = collect_sweep(root).jobs
    assert sorted(int(j.overrides[THETA]) for j in jobs) == [15, 50, 100, 200]
    for job in jobs:
        assert job.status == "ok" and job.metrics["frames"] == 12 and job.job_dir is not None
        config = yaml.safe_load((job.job_dir / "config.yaml").read_text())
        assert config["pipeline"]["loop_closing"]["theta_min"] == int(job.overrides[THETA])
    report = slamkit("report", str(root), cwd=tmp_path, timeout=120)
    assert report.returncode == 0 and len(report.stdout.splitlines()) >= 6
