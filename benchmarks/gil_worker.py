"""GIL benchmark: main-thread Python throughput while a local BA runs inline in a thread vs in the worker process.

Usage: python benchmarks/gil_worker.py [--quick]. Prints both ratios (1.0 = no slowdown vs an idle interpreter).
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from slamkit.bench.optimizer import machine_info, run_gil_bench
from slamkit.optim.synthetic import make_bundle_problem
from slamkit.plugins import ComponentRegistry


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="smaller BA, 1 s windows")
    parser.add_argument("--backend", default="gtsam", help="optimizer name (default gtsam)")
    args = parser.parse_args()
    rng = np.random.default_rng(2015)
    if args.quick:
        problem = make_bundle_problem(rng, n_free=5, n_fixed=5, n_points=500, n_obs=4000)[0]
    else:
        problem = make_bundle_problem(rng)[0]
    result = run_gil_bench(ComponentRegistry.discover(), args.backend, problem, 1.0 if args.quick else 3.0)
    print(json.dumps({"machine": machine_info(), **result}, indent=2))
    print(
        f"inline thread: {result['inline_thread_ratio']:.3f} of idle throughput; "
        f"worker process: {result['worker_process_ratio']:.3f}"
    )


if __name__ == "__main__":
    main()
