"""Sweep reports: read a Hydra multirun directory (``collect``), aggregate its jobs over seeds (``aggregate``),
render the table as text, Markdown or CSV (``table``) and plot it (``plots``); ``slamkit report`` is ``cli``."""

from slamkit.report.aggregate import DEFAULT_METRICS, Metric, Report, SettingRow, Stat, aggregate
from slamkit.report.collect import JobResult, Sweep, collect_sweep, expected_jobs, load_job
from slamkit.report.plots import plot_report
from slamkit.report.table import render_csv, render_markdown, render_text

__all__ = [
    "DEFAULT_METRICS",
    "JobResult",
    "Metric",
    "Report",
    "SettingRow",
    "Stat",
    "Sweep",
    "aggregate",
    "collect_sweep",
    "expected_jobs",
    "load_job",
    "plot_report",
    "render_csv",
    "render_markdown",
    "render_text",
]
