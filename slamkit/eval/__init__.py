"""slamkit.eval: evaluation of trajectories against ground truth (ATE/RPE with evo, plots, CLI) and of runs.

Trajectory files (TUM/KITTI/EuRoC) are read and written by ``slamkit.io.trajectory_io``.
Modules: ``metrics`` (compute_ate, compute_rpe, apply_sim3), ``plot``
(plot_trajectories), ``cli`` (add_eval_parser, run_eval), ``run_metrics`` (a run's metrics.json: counts, timings,
ATE, false loops), ``run_record`` (a run's account rebuilt from its lifecycle events) and ``outputs`` (the
built-in plugin that writes the run directory on the lifecycle hooks). The names below are imported lazily so that
``import slamkit.eval.cli`` (done by every ``slamkit`` command) does not load evo, scipy or matplotlib.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "compute_ate": "metrics",
    "compute_rpe": "metrics",
    "apply_sim3": "metrics",
    "AteResult": "metrics",
    "RpeResult": "metrics",
    "plot_trajectories": "plot",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
