"""Reading a multirun directory: each job's state from its files, the pending jobs from multirun.yaml."""

from __future__ import annotations

from pathlib import Path

import pytest

from slamkit.errors import ConfigError
from slamkit.report.collect import collect_sweep, expected_jobs, load_job, override_key, parse_overrides

from .conftest import WriteJob, WriteMultirun, ok_metrics

THETA = "pipeline.loop_closing.theta_min"


def test_override_key_strips_hydra_prefixes_and_keeps_the_value() -> None:
    assert override_key("+sweep=theta_min") == ("sweep", "theta_min")
    assert override_key("++a.b=x=y") == ("a.b", "x=y")
    assert parse_overrides(["seed=1", f"{THETA}=15"]) == {"seed": "1", THETA: "15"}
    with pytest.raises(ConfigError, match="'seed' is not KEY=VALUE"):
        override_key("seed")


def test_each_job_state_comes_from_its_files(tmp_path: Path, job_writer: WriteJob) -> None:
    ok = load_job(job_writer(tmp_path, 0, ["seed=0"], ok_metrics(0, keyframes=12)))
    assert (ok.status, ok.metrics["keyframes"], ok.error, ok.overrides) == ("ok", 12, None, {"seed": "0"})
    failed = load_job(job_writer(tmp_path, 1, ["seed=1"], {"status": "failed", "error": "DatasetError: gone"}))
    assert (failed.status, failed.error) == ("failed", "DatasetError: gone")
    running = load_job(job_writer(tmp_path, 2, ["seed=2"], None))
    assert (running.status, running.metrics) == ("incomplete", {})
    torn = load_job(job_writer(tmp_path, 3, ["seed=3"], '{"status": "o'))
    assert torn.status == "unreadable" and "3/metrics.json" in (torn.error or "")
    silent = load_job(job_writer(tmp_path, 4, ["seed=4"], {"status": "failed"}))
    assert silent.status == "failed" and "without an error message" in (silent.error or "")


def test_expected_jobs_expand_the_sweep_config_and_the_command_line_wins(
    tmp_path: Path, multirun_writer: WriteMultirun
) -> None:
    jobs = expected_jobs(multirun_writer(tmp_path / "a", ["+sweep=theta_min", "dataset.max_frames=20"]))
    assert jobs is not None and len(jobs) == 12  # 4 theta_min x 3 seeds from conf/sweep/theta_min.yaml
    assert {j[THETA] for j in jobs} == {"15", "50", "100", "200"} and {j["seed"] for j in jobs} == {"0", "1", "2"}
    assert all(j["dataset.max_frames"] == "20" and j["sweep"] == "theta_min" for j in jobs)
    one_seed = expected_jobs(multirun_writer(tmp_path / "b", ["+sweep=theta_min", "seed=5"]))
    assert one_seed is not None and [j[THETA] for j in one_seed] == ["15", "50", "100", "200"]
    assert {j["seed"] for j in one_seed} == {"5"}
    assert expected_jobs(tmp_path / "missing.yaml") is None


def test_a_partial_sweep_lists_started_and_pending_jobs(
    tmp_path: Path, job_writer: WriteJob, multirun_writer: WriteMultirun
) -> None:
    multirun_writer(tmp_path, ["+sweep=theta_min", "seed=0"])
    job_writer(tmp_path, 0, [f"{THETA}=15", "seed=0", "+sweep=theta_min"], ok_metrics(0))
    job_writer(tmp_path, 1, [f"{THETA}=50", "seed=0", "+sweep=theta_min"], None)
    sweep = collect_sweep(tmp_path)
    assert [(j.overrides[THETA], j.status) for j in sweep.jobs] == [
        ("15", "ok"),
        ("50", "incomplete"),
        ("100", "pending"),
        ("200", "pending"),
    ]
    assert sweep.varying_keys(exclude=("seed",)) == [THETA]


def test_without_multirun_yaml_the_job_directories_are_the_sweep(tmp_path: Path, job_writer: WriteJob) -> None:
    for num in (10, 2):  # numeric order, not text order
        job_writer(tmp_path / "sub", num, [f"x={num}"], ok_metrics(0))
    assert [j.overrides["x"] for j in collect_sweep(tmp_path).jobs] == ["2", "10"]


def test_bad_directories_are_named(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"nowhere: no such multirun directory"):
        collect_sweep(tmp_path / "nowhere")
    with pytest.raises(ConfigError, match=r"no job found"):
        collect_sweep(tmp_path)
    (tmp_path / "multirun.yaml").write_text(
        "hydra:\n  sweeper:\n    _target_: hydra._internal.core_plugins.basic_sweeper.BasicSweeper\n"
        "    params:\n      a: '1,(2'\n"
    )
    with pytest.raises(ConfigError, match=r"multirun.yaml: cannot expand the sweep's jobs"):
        collect_sweep(tmp_path)
