"""slamkit.eval: trajectory files (TUM/KITTI/EuRoC) and their evaluation (ATE/RPE with evo, plots, CLI).

Modules: ``trajectory_io`` (read/write/detect), ``metrics`` (compute_ate, compute_rpe, apply_sim3), ``plot``
(plot_trajectories), ``cli`` (add_eval_parser, run_eval). The names below are imported lazily so that
``import slamkit.eval.cli`` (done by every ``slamkit`` command) does not load evo, scipy or matplotlib.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "read_trajectory": "trajectory_io",
    "write_trajectory": "trajectory_io",
    "detect_format": "trajectory_io",
    "read_times": "trajectory_io",
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
