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
