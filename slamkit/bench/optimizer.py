"""``slamkit bench optimizer``: wall time and final cost of every registered optimizer backend.

Problems (slamkit.optim.synthetic, fixed seeds): a local BA the size the issue asks for (10 free + 10 fixed
keyframes, 2000 points, 20000 observations, 1 px noise, 2 % outliers) and an essential graph the size of
ORB-SLAM's KITTI 09 study (1600 keyframes, 2000 edges, Sim3). Each backend is built inline from its default
config node; wall times are medians over 5 runs (local-BA rows interleaved). ``final_cost`` is recomputed from each result with
slamkit.optim.costs (the same definition for every backend: Huber cost of the observations the result keeps,
or the pose-graph cost), so backends compare on equal terms. A backend offering ``reference_bundle_adjust``
(GTSAM: a bare script with the same factors and iterations) adds a ``<name>_bare`` row.

Real problems (``--problems DIR``): the BundleProblems a run recorded (benchmarks/capture_ba_problems.py pickles
every local/global BA of a ``slamkit run``); up to ``--max-problems`` of them, evenly spaced, each solved by every
backend ``--rounds`` times round-robin (so load hits all backends alike); per backend the median over problems of
its per-problem median wall time, and the median over problems of its per-problem time ratio to ``scipy``.

The GIL benchmark measures a pure-Python counting loop in the main thread while a local BA runs (a) inline in a
thread and (b) in the worker process, relative to the same loop on an idle interpreter.
"""

from __future__ import annotations

import argparse
import functools
import json
import platform
import statistics
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from slamkit.interfaces import Optimizer
from slamkit.optim.costs import bundle_cost, essential_graph_cost
from slamkit.optim.factory import build_optimizer
from slamkit.optim.synthetic import make_bundle_problem, make_essential_graph_problem
from slamkit.plugins import ComponentRegistry
from slamkit.problems import BundleProblem, BundleResult

__all__ = [
    "add_bench_optimizer_arguments",
    "machine_info",
    "run_bench_optimizer",
    "run_gil_bench",
    "run_optimizer_bench",
    "run_real_ba_bench",
]


def machine_info() -> dict[str, Any]:
    """nproc, CPU model (from /proc/cpuinfo when readable), Python version, date, 1-minute load average."""
    import os

    model = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "nproc": os.cpu_count(),
        "cpu": model,
        "python": platform.python_version(),
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        # other processes compete for the cores: timings under load are not comparable across runs
        "load_average_1min": round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None,
    }


def _median_time(fn: Callable[[], Any], repeats: int) -> tuple[float, Any]:
    times: list[float] = []
    out: Any = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def _optimizers(registry: ComponentRegistry) -> dict[str, Optimizer]:
    out: dict[str, Optimizer] = {}
    for comp in registry.components("optimizer"):
        node = comp.config_node()
        node["worker"] = "inline"
        out[comp.spec.name] = build_optimizer(node, registry)
    return out


def _ba_problem(quick: bool) -> BundleProblem:
    rng = np.random.default_rng(2015)
    if quick:
        return make_bundle_problem(rng, n_free=5, n_fixed=5, n_points=500, n_obs=4000)[0]
    return make_bundle_problem(
        rng, n_free=10, n_fixed=10, n_points=2000, n_obs=20000, noise_px=1.0, outlier_ratio=0.02
    )[0]


def _ba_row(problem: BundleProblem, wall: float, result: BundleResult) -> dict[str, Any]:
    return {
        "wall_s": round(wall, 4),
        "final_cost": bundle_cost(problem, result.T_c_w, result.xyz_w, ~result.outlier),
        "initial_cost": bundle_cost(problem, problem.T_c_w, problem.xyz_w),
        "iterations": int(result.iterations),
        "outliers": int(result.outlier.sum()),
    }


def run_real_ba_bench(
    problems_dir: Path, max_problems: int = 20, rounds: int = 3, registry: ComponentRegistry | None = None
) -> dict[str, Any]:
    """Time every backend's bundle_adjust on recorded problems (``ba_*.pkl`` in ``problems_dir``; trusted pickles
    written by benchmarks/capture_ba_problems.py). Returns per-backend medians, per-problem ratios to ``scipy``
    and the largest keyframe-position difference to ``scipy`` (m)."""
    import pickle

    paths = sorted(problems_dir.glob("ba_*.pkl"))
    if not paths:
        raise FileNotFoundError(f"no ba_*.pkl in {problems_dir}")
    step = max(1, len(paths) // max(1, max_problems))
    paths = paths[::step][:max_problems]
    optimizers = _optimizers(registry if registry is not None else ComponentRegistry.discover())
    problems: list[BundleProblem] = [pickle.loads(p.read_bytes()) for p in paths]
    for opt in optimizers.values():  # warm-up (numba compilation, imports)
        opt.bundle_adjust(problems[0])
    walls: dict[str, list[float]] = {name: [] for name in optimizers}
    diffs: dict[str, list[float]] = {name: [] for name in optimizers}
    iterations: dict[str, list[int]] = {name: [] for name in optimizers}
    for problem in problems:
        per: dict[str, list[float]] = {name: [] for name in optimizers}
        results: dict[str, BundleResult] = {}
        for _ in range(rounds):
            for name, opt in optimizers.items():
                t0 = time.perf_counter()
                results[name] = opt.bundle_adjust(problem)
                per[name].append(time.perf_counter() - t0)
        reference = results.get("scipy", next(iter(results.values())))
        for name in optimizers:
            walls[name].append(statistics.median(per[name]))
            iterations[name].append(int(results[name].iterations))
            diffs[name].append(float(np.abs(results[name].T_c_w[:, :3, 3] - reference.T_c_w[:, :3, 3]).max()))
    out: dict[str, Any] = {
        "dir": str(problems_dir),
        "problems": len(problems),
        "rounds": rounds,
        "observations_median": int(statistics.median(len(p.obs_pose) for p in problems)),
        "backends": {},
    }
    base = walls.get("scipy")
    for name in optimizers:
        row: dict[str, Any] = {
            "wall_ms_median": round(1e3 * statistics.median(walls[name]), 1),
            "iterations_median": statistics.median(iterations[name]),
            "max_position_diff_to_scipy_m": max(diffs[name]),
        }
        if base is not None:
            row["time_ratio_to_scipy_median"] = round(
                statistics.median(w / b for w, b in zip(walls[name], base, strict=True)), 3
            )
        out["backends"][name] = row
    return out


def run_optimizer_bench(json_path: Path | None, quick: bool, gil: bool = True) -> dict[str, Any]:
    """Run the benchmarks; write the JSON to ``json_path`` when given; return it.

    quick: smaller problems and one repeat (a smoke run); the full run repeats each measurement 5 times
    (local-BA rows interleaved round-robin) and reports medians.
    gil: also run the GIL benchmark (key "gil").
    """
    registry = ComponentRegistry.discover()
    optimizers = _optimizers(registry)
    repeats = 1 if quick else 5
    report: dict[str, Any] = {"machine": machine_info(), "quick": quick, "local_ba": {}, "essential_graph": {}}
    notes: list[str] = []
    if "scipy" not in optimizers:
        notes.append("optimizer=scipy is not registered: no scipy rows")

    ba = _ba_problem(quick)
    report["local_ba_problem"] = {
        "keyframes_free": int((~ba.pose_fixed).sum()),
        "keyframes_fixed": int(ba.pose_fixed.sum()),
        "points": len(ba.xyz_w),
        "observations": len(ba.obs_pose),
    }
    # Interleaved (round-robin) repeats: load from other processes then hits every row alike.
    runs: dict[str, Callable[[], BundleResult]] = {}
    for name, opt in optimizers.items():
        runs[name] = functools.partial(opt.bundle_adjust, ba)
        reference = getattr(opt, "reference_bundle_adjust", None)
        if callable(reference):
            runs[f"{name}_bare"] = functools.partial(reference, ba)
    times: dict[str, list[float]] = {key: [] for key in runs}
    results: dict[str, BundleResult] = {}
    for _ in range(repeats):
        for key, fn in runs.items():
            t0 = time.perf_counter()
            results[key] = fn()
            times[key].append(time.perf_counter() - t0)
    for key in runs:
        report["local_ba"][key] = _ba_row(ba, statistics.median(times[key]), results[key])
    for name in optimizers:
        if f"{name}_bare" in runs:
            report["local_ba"][f"{name}_vs_bare_time_ratio"] = round(
                report["local_ba"][name]["wall_s"] / report["local_ba"][f"{name}_bare"]["wall_s"], 3
            )

    rng = np.random.default_rng(2009)
    eg = (
        make_essential_graph_problem(rng, n_keyframes=400, n_edges=500)[0]
        if quick
        else make_essential_graph_problem(rng, n_keyframes=1600, n_edges=2000)[0]
    )
    report["essential_graph_problem"] = {"keyframes": len(eg.S_c_w), "edges": len(eg.edge_i), "sim3": eg.use_sim3}
    for name, opt in optimizers.items():
        wall, result = _median_time(functools.partial(opt.optimize_essential_graph, eg), repeats)
        report["essential_graph"][name] = {
            "wall_s": round(wall, 4),
            "final_cost": essential_graph_cost(eg, result.S_c_w),
            "initial_cost": essential_graph_cost(eg, eg.S_c_w),
            "iterations": int(result.iterations),
        }
    for section in ("local_ba", "essential_graph"):
        rows = report[section]
        if "gtsam" in rows and "scipy" in rows:
            rows["scipy_vs_gtsam_time_ratio"] = round(rows["scipy"]["wall_s"] / rows["gtsam"]["wall_s"], 3)
            rows["scipy_vs_gtsam_cost_ratio"] = rows["scipy"]["final_cost"] / rows["gtsam"]["final_cost"]
    if gil:
        gil_backend = "gtsam" if "gtsam" in optimizers else next(iter(optimizers), None)
        if gil_backend is not None:
            report["gil"] = run_gil_bench(registry, gil_backend, ba, duration_s=1.0 if quick else 3.0)
    if notes:
        report["notes"] = notes
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(report, indent=2) + "\n")
    return report


def _count_for(duration_s: float) -> float:
    """Iterations per second of a pure-Python loop run for ``duration_s`` in the calling thread."""
    n = 0
    t0 = time.perf_counter()
    end = t0 + duration_s
    while True:
        for _ in range(1000):
            n += 1
        if time.perf_counter() >= end:
            break
    return n / (time.perf_counter() - t0)


def _count_while_busy(opt: Optimizer, problem: BundleProblem, duration_s: float) -> tuple[float, int]:
    """Main-thread loop rate while a thread runs bundle_adjust back to back; (rate, BAs completed)."""
    stop = threading.Event()
    done = [0]
    started = threading.Event()

    def work() -> None:
        while not stop.is_set():
            started.set()
            opt.bundle_adjust(problem)
            done[0] += 1

    thread = threading.Thread(target=work, daemon=True)
    thread.start()
    started.wait()
    time.sleep(0.05)  # let the solve get going
    rate = _count_for(duration_s)
    stop.set()
    thread.join()
    return rate, done[0]


def run_gil_bench(
    registry: ComponentRegistry, name: str, problem: BundleProblem, duration_s: float = 3.0
) -> dict[str, Any]:
    """Main-thread Python throughput while optimizer ``name`` runs local BAs (a) inline in a thread and (b) in
    its worker process, relative to idle. Returns rates (loop iterations/s) and ratios."""
    node = registry.get("optimizer", name).config_node()
    node["worker"] = "inline"
    inline = build_optimizer(node, registry)
    idle = _count_for(duration_s)
    inline_rate, inline_done = _count_while_busy(inline, problem, duration_s)
    node["worker"] = "process"
    from slamkit.optim.worker import ProcessOptimizer

    worker = build_optimizer(node, registry)
    try:
        worker_rate, worker_done = _count_while_busy(worker, problem, duration_s)
    finally:
        if isinstance(worker, ProcessOptimizer):
            worker.close()
    idle_after = _count_for(duration_s)
    idle_rate = max(idle, idle_after)
    return {
        "backend": name,
        "duration_s": duration_s,
        "idle_rate_per_s": round(idle_rate),
        "inline_thread_rate_per_s": round(inline_rate),
        "worker_process_rate_per_s": round(worker_rate),
        "inline_thread_ratio": round(inline_rate / idle_rate, 3),
        "worker_process_ratio": round(worker_rate / idle_rate, 3),
        "bundle_adjustments_inline": inline_done,
        "bundle_adjustments_worker": worker_done,
    }


def add_bench_optimizer_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``slamkit bench optimizer``."""
    parser.add_argument("--json", type=Path, default=None, metavar="FILE", help="write the results as JSON here")
    parser.add_argument("--quick", action="store_true", help="small problems, one repeat (smoke run)")
    parser.add_argument("--no-gil", action="store_true", help="skip the GIL (inline thread vs worker) benchmark")
    parser.add_argument(
        "--problems",
        type=Path,
        default=None,
        metavar="DIR",
        help="only time recorded local BAs (ba_*.pkl from benchmarks/capture_ba_problems.py; trusted files)",
    )
    parser.add_argument(
        "--max-problems", type=int, default=20, help="with --problems: at most this many, evenly spaced"
    )
    parser.add_argument("--rounds", type=int, default=3, help="with --problems: solves per backend and problem")


def run_bench_optimizer(args: argparse.Namespace) -> int:
    """Run the benchmark from parsed arguments, print a summary; exit code 0."""
    if args.problems is not None:
        real = {
            "machine": machine_info(),
            "real_local_ba": run_real_ba_bench(args.problems, args.max_problems, args.rounds),
        }
        if args.json is not None:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(real, indent=2) + "\n")
        r = real["real_local_ba"]
        print(
            f"real local BAs: {r['problems']} problems from {r['dir']} ({r['rounds']} rounds, median {r['observations_median']} observations)"
        )
        for name, row in r["backends"].items():
            ratio = row.get("time_ratio_to_scipy_median")
            print(
                f"  {name:12s} median {row['wall_ms_median']:8.1f} ms  iterations {row['iterations_median']}"
                + (f"  time / scipy (per-problem median) {ratio:.2f}" if ratio is not None else "")
                + f"  max position diff to scipy {row['max_position_diff_to_scipy_m']:.2e} m"
            )
        return 0
    report = run_optimizer_bench(args.json, bool(args.quick), gil=not args.no_gil)
    for section in ("local_ba", "essential_graph"):
        print(f"{section}:")
        for key, row in report[section].items():
            if isinstance(row, dict):
                print(
                    f"  {key:12s} wall {row['wall_s']:8.3f} s  final cost {row['final_cost']:.6g}  "
                    f"iterations {row['iterations']}"
                )
            else:
                print(f"  {key}: {row}")
    if "gil" in report:
        g = report["gil"]
        print(
            f"gil ({g['backend']}): main-thread Python throughput vs idle: inline thread {g['inline_thread_ratio']:.3f}, "
            f"worker process {g['worker_process_ratio']:.3f}"
        )
    for note in report.get("notes", []):
        print(f"note: {note}")
    return 0
