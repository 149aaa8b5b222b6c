"""``slamkit report MULTIRUN_DIR``: the table of a sweep (a row per setting, median [min, max] over seeds) on the
terminal, as CSV and Markdown, and a PNG of accuracy and optimization time against the swept value.

``add_report_parser(subparsers)`` registers the subcommand (its handler is ``args.func = run_report``);
``run_report(args)`` returns the exit code: 0 (also when some jobs failed or are still pending: the table says
so), 2 on bad input (one line on stderr, through ``slamkit.cli.main``).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from slamkit.report.aggregate import SEED_KEY, aggregate
from slamkit.report.collect import collect_sweep
from slamkit.report.plots import plot_report
from slamkit.report.table import render_csv, render_markdown, render_text

REPORT_MD = "report.md"
REPORT_PNG = "report.png"


def add_report_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register the ``report`` subcommand on an argparse ``_SubParsersAction`` and return its parser."""
    p: argparse.ArgumentParser = subparsers.add_parser(
        "report",
        help="table and plots of a sweep (`slamkit run -m ...`): a row per setting over seeds",
        description=(
            "Aggregate the jobs of a Hydra multirun directory: one row per setting (the swept values other than "
            "the seed) with the median [min, max] over seeds of accuracy, essential-graph edges and time, loops, "
            "map size and timings. Failed jobs are listed with their error; jobs still running or not started "
            "are counted. Writes MULTIRUN_DIR/report.md and MULTIRUN_DIR/report.png unless told otherwise."
        ),
    )
    p.add_argument("multirun_dir", type=Path, metavar="MULTIRUN_DIR", help="Hydra sweep dir (multirun/DATE/TIME)")
    p.add_argument("--csv", type=Path, default=None, metavar="FILE", help="also write the table as CSV")
    p.add_argument(
        "--markdown",
        type=Path,
        default=None,
        metavar="FILE",
        help=f"Markdown table (default: MULTIRUN_DIR/{REPORT_MD})",
    )
    p.add_argument(
        "--plot", type=Path, default=None, metavar="FILE.png", help=f"plots (default: MULTIRUN_DIR/{REPORT_PNG})"
    )
    p.add_argument("--no-plot", action="store_true", help="write no plot")
    p.add_argument("--seed-key", default=SEED_KEY, help="override aggregated over (default: seed)")
    p.set_defaults(func=run_report)
    return p


def run_report(args: argparse.Namespace) -> int:
    """Print the sweep's table; write Markdown, optional CSV and the plot. Raises ConfigError on a bad dir."""
    root: Path = args.multirun_dir
    report = aggregate(collect_sweep(root), seed_key=args.seed_key)
    print(render_text(report), end="")
    md_path: Path = args.markdown or root / REPORT_MD
    md_path.write_text(render_markdown(report))
    written = [md_path]
    if args.csv is not None:
        args.csv.write_text(render_csv(report))
        written.append(args.csv)
    if not args.no_plot:
        plot_path: Path = args.plot or root / REPORT_PNG
        if plot_report(report, plot_path, title=str(root)):
            written.append(plot_path)
    print("\nwrote " + ", ".join(str(p) for p in written))
    return 0
