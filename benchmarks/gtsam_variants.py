"""GTSAM backend settings against each other on recorded local BAs, round-robin in one process.

Usage: ``python benchmarks/gtsam_variants.py DIR N VARIANT[,VARIANT...] [ROUNDS] [cpu]`` with DIR holding the
``ba_*.pkl`` of ``benchmarks/capture_ba_problems.py`` (trusted files: pickles), N problems evenly spaced, e.g.
``python benchmarks/gtsam_variants.py /tmp/ba_room 20 scipy,main,noskip,gtsam``.

Variants: ``scipy`` (the default backend), ``gtsam`` (this tree's defaults), ``main`` (the GTSAM backend of the
checkout at $SLAMKIT_MAIN, default /work/main: before/after in one process), ``noskip``
(``ba_skip_converged_second_stage: false``), ``tol7`` / ``tol10`` (``relative_error_tol`` 1e-7 / 1e-10, the
default backend's), ``lm`` (``ba_gauss_newton: false``: GTSAM's LM for every stage), ``free`` (``ba_fix_scale_gauge: false``: a
monocular window with one fixed keyframe leaves its scale to LM's damping). Per problem: the median time of ROUNDS solves, iterations, outliers, final cost and keyframe
positions relative to the first variant's; then medians over the problems. ``cpu``: time the process's CPU
time (``time.process_time``, all threads) instead of the wall clock: on a machine shared with other runs it
leaves out the time the process waited for a core.
"""

from __future__ import annotations

import importlib.util
import os
import pickle
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np


def _scipy() -> Any:
    from slamkit.optim.factory import build_optimizer
    from slamkit.plugins import ComponentRegistry

    registry = ComponentRegistry.discover()
    node = registry.get("optimizer", "scipy").config_node()
    node["worker"] = "inline"
    return build_optimizer(node, registry)


def _main_checkout() -> Any:
    path = Path(os.environ.get("SLAMKIT_MAIN", "/work/main")) / "plugins/slamkit_gtsam/backend.py"
    spec = importlib.util.spec_from_file_location("main_gtsam_backend", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["main_gtsam_backend"] = module
    spec.loader.exec_module(module)
    return module.GtsamOptimizer()


def _gtsam(**kwargs: Any) -> Callable[[], Any]:
    def make() -> Any:
        from slamkit_gtsam.backend import GtsamOptimizer

        return GtsamOptimizer(**kwargs)

    return make


VARIANTS: dict[str, Callable[[], Any]] = {
    "scipy": _scipy,
    "main": _main_checkout,
    "gtsam": _gtsam(),
    "noskip": _gtsam(ba_skip_converged_second_stage=False),
    "tol7": _gtsam(relative_error_tol=1e-7),
    "tol10": _gtsam(relative_error_tol=1e-10),
    "keep1": _gtsam(ba_drop_undetermined_points=False),
    "predict": _gtsam(ba_predict_convergence=True),
    "mfchol": _gtsam(ba_linear_solver="MULTIFRONTAL_CHOLESKY"),
    "lm": _gtsam(ba_gauss_newton=False),
    "free": _gtsam(ba_fix_scale_gauge=False),
}


def main(argv: list[str]) -> int:
    """Run the comparison (module docstring); exit code 0, 2 on bad arguments."""
    if len(argv) < 3 or any(v not in VARIANTS for v in argv[2].split(",")):
        print(__doc__)
        return 2
    paths = sorted(Path(argv[0]).glob("ba_*.pkl"))
    n, names = int(argv[1]), argv[2].split(",")
    rounds = int(argv[3]) if len(argv) > 3 else 1
    clock = time.process_time if len(argv) > 4 and argv[4] == "cpu" else time.perf_counter
    paths = paths[:: max(1, len(paths) // n)][:n]
    opts = {k: VARIANTS[k]() for k in names}
    warm = pickle.loads(paths[0].read_bytes())
    for opt in opts.values():
        opt.bundle_adjust(warm)  # JIT and imports out of the timings
    times: dict[str, list[float]] = {k: [] for k in names}
    iters: dict[str, list[int]] = {k: [] for k in names}
    dpos: dict[str, list[float]] = {k: [] for k in names}
    cost: dict[str, list[float]] = {k: [] for k in names}
    for path in paths:
        problem = pickle.loads(path.read_bytes())
        per: dict[str, list[float]] = {k: [] for k in names}
        results: dict[str, Any] = {}
        for _ in range(rounds):
            for k in names:
                t0 = clock()
                results[k] = opts[k].bundle_adjust(problem)
                per[k].append(clock() - t0)
        ref = results[names[0]]
        for k in names:
            r = results[k]
            times[k].append(statistics.median(per[k]))
            iters[k].append(int(r.iterations))
            dpos[k].append(float(np.abs(r.T_c_w[:, :3, 3] - ref.T_c_w[:, :3, 3]).max()))
            cost[k].append(float(r.cost_final) / max(float(ref.cost_final), 1e-300))
        print(
            f"{path.name} K={len(problem.T_c_w)} M={len(problem.xyz_w)} E={len(problem.obs_pose)} "
            + " ".join(
                f"{k}={times[k][-1] * 1e3:.0f}ms/{iters[k][-1]}it/out{int(results[k].outlier.sum())}"
                f"/d{dpos[k][-1] * 1e3:.3f}mm"
                for k in names
            ),
            flush=True,
        )
    base = np.array(times[names[0]])
    for k in names:
        t = np.array(times[k])
        print(
            f"{k:8s} median {statistics.median(times[k]) * 1e3:7.1f} ms, sum {t.sum():6.2f} s, "
            f"per-problem ratio to {names[0]} {float(np.median(t / base)):.3f}, iterations {statistics.median(iters[k])}, "
            f"|dpos| median/max {statistics.median(dpos[k]) * 1e3:.4f}/{max(dpos[k]) * 1e3:.3f} mm, "
            f"cost ratio median {statistics.median(cost[k]):.5f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
