"""The report's table in three forms: aligned text for the terminal, Markdown, and CSV (one column per statistic).

A cell is the median over seeds, with ``[min, max]`` when the seeds disagree; ``-`` when no finished job of the
setting has the metric (e.g. no loop closed, so no essential graph). Failed jobs are listed under the table with
their error.
"""

from __future__ import annotations

import csv
import io

from slamkit.report.aggregate import Metric, Report, SettingRow, Stat

EMPTY = "-"


def short_key(key: str, keys: list[str]) -> str:
    """``pipeline.loop_closing.theta_min`` -> ``theta_min``, unless two swept keys end alike."""
    last = key.rsplit(".", 1)[-1]
    return last if sum(k.rsplit(".", 1)[-1] == last for k in keys) == 1 else key


def format_stat(stat: Stat | None, fmt: str) -> str:
    """``median`` or ``median [min, max]`` in the metric's format; ``-`` for no value."""
    if stat is None:
        return EMPTY
    median = fmt % stat.median
    lo, hi = fmt % stat.min, fmt % stat.max
    return median if lo == hi else f"{median} [{lo}, {hi}]"


def _shown_metrics(report: Report) -> list[Metric]:
    """The metrics that at least one setting has (a sweep without ground truth has no ATE column)."""
    return [m for m in report.metrics if any(r.stats.get(m.key) is not None for r in report.rows)]


def _cells(report: Report) -> tuple[list[str], list[list[str]]]:
    metrics = _shown_metrics(report)
    headers = [short_key(k, report.keys) for k in report.keys] or ["setting"]
    headers += ["jobs", *(m.header for m in metrics)]
    rows = []
    for row in report.rows:
        label = [row.setting[k] for k in report.keys] or ["all"]
        rows.append([*label, row.status, *(format_stat(row.stats.get(m.key), m.fmt) for m in metrics)])
    return headers, rows


def _failures(report: Report) -> list[str]:
    lines = []
    for row in report.rows:
        label = " ".join(f"{short_key(k, report.keys)}={v}" for k, v in row.setting.items())
        for seed, error in row.errors():
            lines.append(f"{label} seed={seed}: {error}".strip())
    return lines


def _first_line(text: str) -> str:
    return text.strip().splitlines()[0] if text.strip() else text


def render_text(report: Report) -> str:
    """The table for a terminal (columns aligned, numbers right-aligned), then the failed jobs."""
    headers, rows = _cells(report)
    n_label = max(len(report.keys), 1)
    widths = [max(len(h), *(len(r[i]) for r in rows)) if rows else len(h) for i, h in enumerate(headers)]

    def line(cells: list[str]) -> str:
        return "  ".join(
            c.ljust(w) if i < n_label + 1 else c.rjust(w) for i, (c, w) in enumerate(zip(cells, widths, strict=True))
        ).rstrip()

    out = [line(headers), "  ".join("-" * w for w in widths), *(line(r) for r in rows)]
    failures = _failures(report)
    if failures:
        out += ["", "failed jobs:", *(f"  {_first_line(f)}" for f in failures)]
    return "\n".join(out) + "\n"


def _md_escape(cell: str) -> str:
    return cell.replace("|", "\\|")


def render_markdown(report: Report) -> str:
    """The table as GitHub Markdown (label columns left-aligned, metrics right-aligned), then the failed jobs."""
    headers, rows = _cells(report)
    n_label = max(len(report.keys), 1)
    align = ["---"] * (n_label + 1) + ["---:"] * (len(headers) - n_label - 1)
    out = [
        "| " + " | ".join(headers) + " |",
        "| " + " | ".join(align) + " |",
        *("| " + " | ".join(_md_escape(c) for c in r) + " |" for r in rows),
    ]
    failures = _failures(report)
    if failures:
        out += ["", "Failed jobs:", "", *(f"- `{_first_line(f)}`" for f in failures)]
    return "\n".join(out) + "\n"


def render_csv(report: Report) -> str:
    """One line per setting: the swept values, job counts by state, then ``<metric>_median/_min/_max/_n`` of every
    metric (empty when none), and the failed jobs' errors (``seed=S: error``, joined by `` | ``)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    statuses = ("ok", "failed", "unreadable", "incomplete", "pending")
    header = [*report.keys, "jobs", *(f"jobs_{s}" for s in statuses)]
    for m in report.metrics:
        header += [f"{m.key}_median", f"{m.key}_min", f"{m.key}_max", f"{m.key}_n"]
    writer.writerow([*header, "errors"])
    for row in report.rows:
        writer.writerow(_csv_row(report, row, statuses))
    return buf.getvalue()


def _csv_row(report: Report, row: SettingRow, statuses: tuple[str, ...]) -> list[str]:
    cells = [row.setting[k] for k in report.keys] + [str(len(row.jobs))] + [str(row.count(s)) for s in statuses]
    for m in report.metrics:
        stat = row.stats.get(m.key)
        cells += ["", "", "", "0"] if stat is None else [repr(stat.median), repr(stat.min), repr(stat.max), str(stat.n)]
    cells.append(" | ".join(f"seed={seed}: {_first_line(err)}" for seed, err in row.errors()))
    return cells
