"""Aggregating a sweep's jobs: one row per setting (the swept values other than the seed), each metric's median,
min and max over the seeds that finished."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from slamkit.report.collect import JobResult, Sweep

SEED_KEY = "seed"


def _number(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        return None
    return float(value)


def _scalar_or_list(scalar_key: str, list_key: str, reduce: Callable[[list[float]], float]) -> Callable[..., Any]:
    """A metric read from its scalar summary, or reduced from the per-loop list when a run predates the summary."""

    def get(metrics: dict[str, Any]) -> float | None:
        if scalar_key in metrics:
            return _number(metrics[scalar_key])
        values = [v for v in (_number(x) for x in metrics.get(list_key) or []) if v is not None]
        return reduce(values) if values else None

    return get


@dataclass(frozen=True)
class Metric:
    """A column of the report: ``key`` in metrics.json (or a getter), header, and printf format of a value."""

    key: str
    header: str
    fmt: str
    getter: Callable[[dict[str, Any]], float | None] | None = None

    def value(self, metrics: dict[str, Any]) -> float | None:
        """This metric of one job (None when absent, not a finite number, or e.g. no loop closed)."""
        return self.getter(metrics) if self.getter is not None else _number(metrics.get(self.key))


#: The report's columns: accuracy, the essential graph (ORB-SLAM Table VI), loops, map size, timings.
DEFAULT_METRICS: tuple[Metric, ...] = (
    Metric("kf_ate_rmse_m", "KF ATE m", "%.4f"),
    Metric("ate_rmse_m", "ATE m", "%.4f"),
    Metric(
        "essential_graph_edges_max",
        "EG edges",
        "%.0f",
        _scalar_or_list("essential_graph_edges_max", "essential_graph_edges", max),
    ),
    Metric(
        "essential_graph_ms_total",
        "EG ms",
        "%.0f",
        _scalar_or_list("essential_graph_ms_total", "essential_graph_ms", sum),
    ),
    Metric("loop_correction_ms_total", "loop corr ms", "%.0f"),
    Metric("loops_closed", "loops", "%.0f"),
    Metric("keyframes", "KFs", "%.0f"),
    Metric("map_points", "points", "%.0f"),
    Metric("local_ba_ms_median", "local BA ms", "%.0f"),
    Metric("tracking_ms_median", "track ms", "%.1f"),
    Metric("wall_s", "wall s", "%.0f"),
)


@dataclass(frozen=True)
class Stat:
    """Median, min and max of a metric over the seeds of one setting that have it (``n`` of them)."""

    median: float
    min: float
    max: float
    n: int

    @staticmethod
    def of(values: Sequence[float]) -> Stat | None:
        """The statistic of ``values`` (None when empty)."""
        if not values:
            return None
        arr = np.asarray(values, dtype=np.float64)
        return Stat(float(np.median(arr)), float(arr.min()), float(arr.max()), len(arr))


@dataclass(frozen=True)
class SettingRow:
    """One setting of the sweep: its swept values, how its jobs ended, its metrics over seeds."""

    setting: dict[str, str]
    jobs: list[JobResult]
    stats: dict[str, Stat | None]
    values: dict[str, list[float]] = field(default_factory=dict)

    def count(self, status: str) -> int:
        """How many of this setting's jobs are in ``status`` (see ``slamkit.report.collect.STATUSES``)."""
        return sum(j.status == status for j in self.jobs)

    @property
    def status(self) -> str:
        """``"ok 3/3"``, or e.g. ``"ok 1/3, failed 1, pending 1"``."""
        parts = [f"ok {self.count('ok')}/{len(self.jobs)}"]
        parts += [f"{s} {self.count(s)}" for s in ("failed", "unreadable", "incomplete", "pending") if self.count(s)]
        return ", ".join(parts)

    def errors(self) -> list[tuple[str, str]]:
        """``(seed, error)`` of each job of this setting that failed (the seed from the overrides, else the one
        the job recorded in metrics.json)."""
        return [
            (j.overrides.get(SEED_KEY, str(j.metrics.get("seed", "?"))), j.error or "") for j in self.jobs if j.error
        ]


def value_sort_key(value: str) -> tuple[int, float, str]:
    """Numbers in numeric order, before other values in text order."""
    try:
        return (0, float(value), "")
    except ValueError:
        return (1, 0.0, value)


@dataclass(frozen=True)
class Report:
    """A sweep aggregated: the swept keys (columns that name a setting) and one row per setting."""

    keys: list[str]
    rows: list[SettingRow]
    metrics: tuple[Metric, ...]


def aggregate(sweep: Sweep, metrics: tuple[Metric, ...] = DEFAULT_METRICS, seed_key: str = SEED_KEY) -> Report:
    """Group the sweep's jobs by their swept values (every varying override but ``seed_key``), sort the settings
    by those values (numerically where they are numbers) and aggregate each metric over the finished jobs."""
    keys = sweep.varying_keys(exclude=(seed_key,))
    groups: dict[tuple[str, ...], list[JobResult]] = {}
    for job in sweep.jobs:
        groups.setdefault(tuple(job.overrides.get(k, "") for k in keys), []).append(job)
    rows: list[SettingRow] = []
    for values_key in sorted(groups, key=lambda t: [value_sort_key(v) for v in t]):
        jobs = groups[values_key]
        done = [j for j in jobs if j.status == "ok"]
        per_metric: dict[str, list[float]] = {}
        for m in metrics:
            per_metric[m.key] = [v for v in (m.value(j.metrics) for j in done) if v is not None]
        rows.append(
            SettingRow(
                dict(zip(keys, values_key, strict=True)),
                jobs,
                {k: Stat.of(v) for k, v in per_metric.items()},
                per_metric,
            )
        )
    return Report(keys, rows, metrics)
