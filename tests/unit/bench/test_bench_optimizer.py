"""slamkit bench optimizer: the JSON has the issue's shape and its numbers are consistent."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from slamkit.bench.optimizer import add_bench_optimizer_arguments, run_bench_optimizer, run_optimizer_bench
from slamkit.plugins import ComponentRegistry

NAMES = [c.spec.name for c in ComponentRegistry.discover().components("optimizer")]


@pytest.mark.skipif("gtsam" not in NAMES, reason="the gtsam plugin is not registered")
def test_quick_bench_writes_the_issue_json(tmp_path: Path) -> None:
    path = tmp_path / "out" / "bench.json"
    report = run_optimizer_bench(path, quick=True, gil=False)
    on_disk = json.loads(path.read_text())
    assert on_disk == json.loads(json.dumps(report))
    for section, rows in (("local_ba", ["gtsam", "gtsam_bare"]), ("essential_graph", ["gtsam"])):
        for row in rows:
            entry = on_disk[section][row]
            assert entry["wall_s"] > 0 and 0 < entry["final_cost"] < entry["initial_cost"]
    # the bare script runs the same graph for the same iterations: same cost
    ba = on_disk["local_ba"]
    assert ba["gtsam"]["final_cost"] == pytest.approx(ba["gtsam_bare"]["final_cost"], rel=1e-6)
    assert ba["gtsam"]["iterations"] == ba["gtsam_bare"]["iterations"]
    if "scipy" in NAMES:
        assert "scipy" in ba and "scipy" in on_disk["essential_graph"]
    assert on_disk["machine"]["nproc"] >= 1


def test_cli_arguments() -> None:
    parser = argparse.ArgumentParser()
    add_bench_optimizer_arguments(parser)
    args = parser.parse_args(["--json", "x.json", "--quick", "--no-gil"])
    assert args.json == Path("x.json") and args.quick and args.no_gil
    assert callable(run_bench_optimizer)


@pytest.mark.slow
@pytest.mark.skipif("gtsam" not in NAMES, reason="the gtsam plugin is not registered")
def test_gil_bench_worker_keeps_more_throughput_than_inline() -> None:
    report = run_optimizer_bench(None, quick=True, gil=True)
    gil = report["gil"]
    assert gil["worker_process_ratio"] > gil["inline_thread_ratio"]


@pytest.mark.skipif("scipy" not in NAMES or len(NAMES) < 2, reason="needs scipy and another backend")
def test_real_problem_bench_compares_backends_on_recorded_problems(tmp_path: Path) -> None:
    import pickle

    import numpy as np

    from slamkit.bench.optimizer import run_real_ba_bench
    from slamkit.optim.synthetic import make_bundle_problem

    for i in range(3):
        problem = make_bundle_problem(np.random.default_rng(i), n_free=3, n_fixed=2, n_points=120, n_obs=480)[0]
        (tmp_path / f"ba_{i:04d}.pkl").write_bytes(pickle.dumps(problem))
    out = run_real_ba_bench(tmp_path, max_problems=2, rounds=1)
    assert out["problems"] == 2
    assert out["backends"]["scipy"]["time_ratio_to_scipy_median"] == 1.0
    for row in out["backends"].values():
        assert row["wall_ms_median"] > 0
        # every backend reaches the same keyframe positions (within the contract's 1 mm)
        assert row["max_position_diff_to_scipy_m"] < 1e-3
    args = argparse.ArgumentParser()
    add_bench_optimizer_arguments(args)
    parsed = args.parse_args(["--problems", str(tmp_path), "--max-problems", "1", "--rounds", "1"])
    assert run_bench_optimizer(parsed) == 0
