"""PNG plots of a sweep: accuracy (keyframe ATE), essential-graph edges and optimization time against the swept
value. Each setting shows its median over seeds with a min-max bar, and each seed as a faint dot."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slamkit.report.aggregate import Report, value_sort_key
from slamkit.report.table import short_key

#: (metric key, axis label) of each panel; panels no setting has a value for are left out.
PLOT_PANELS: tuple[tuple[str, str], ...] = (
    ("kf_ate_rmse_m", "keyframe ATE RMSE (m, Sim3)"),
    ("essential_graph_edges_max", "essential-graph edges"),
    ("essential_graph_ms_total", "essential-graph time (ms)"),
    ("local_ba_ms_median", "local BA median (ms)"),
)


def _x_positions(report: Report) -> tuple[np.ndarray, list[str], str, bool]:
    """x of each row, tick labels, axis label, and whether the axis is numeric (a single numeric swept key)."""
    labels = [", ".join(r.setting[k] for k in report.keys) or "all" for r in report.rows]
    title = ", ".join(short_key(k, report.keys) for k in report.keys) or "setting"
    numeric = len(report.keys) == 1 and all(value_sort_key(r.setting[report.keys[0]])[0] == 0 for r in report.rows)
    if numeric:
        return np.array([float(r.setting[report.keys[0]]) for r in report.rows]), labels, title, True
    return np.arange(len(report.rows), dtype=np.float64), labels, title, False


def plot_report(report: Report, path: Path, title: str = "") -> list[str]:
    """Write the report's plots to ``path`` (PNG, one panel per metric that has values); returns the metric
    keys plotted (empty, and no file written, when no setting has any of them)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [(k, label) for k, label in PLOT_PANELS if any(r.stats.get(k) is not None for r in report.rows)]
    if not panels:
        return []
    x, labels, x_title, numeric = _x_positions(report)
    ncols = min(2, len(panels))
    nrows = -(-len(panels) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(5.0 * ncols, 3.4 * nrows), squeeze=False)
    for ax in axes.flat[len(panels) :]:
        ax.set_visible(False)
    for ax, (key, label) in zip(axes.flat, panels, strict=False):
        for xi, row in zip(x, report.rows, strict=True):
            seeds = row.values.get(key, [])
            stat = row.stats.get(key)
            if stat is None:
                continue
            ax.scatter(np.full(len(seeds), xi), seeds, s=12, color="0.6", zorder=2)
            ax.errorbar(
                [xi],
                [stat.median],
                yerr=[[stat.median - stat.min], [stat.max - stat.median]],
                fmt="o",
                color="C0",
                capsize=4,
                zorder=3,
            )
        stats = [(xi, r.stats.get(key)) for xi, r in zip(x, report.rows, strict=True)]
        medians = [(xi, st.median) for xi, st in stats if st is not None]
        if numeric and len(medians) > 1:
            ax.plot(*zip(*medians, strict=True), color="C0", lw=1, zorder=1)
        if numeric:
            ax.set_xticks(x)
            pad = 0.06 * (float(x.max() - x.min()) or 1.0)
            ax.set_xlim(float(x.min()) - pad, float(x.max()) + pad)
        else:
            rotate = max(map(len, labels)) > 8
            ax.set_xticks(x, labels, rotation=30 if rotate else 0, ha="right" if rotate else "center")
            ax.set_xlim(-0.5, len(labels) - 0.5)
        ax.set_xlabel(x_title)
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return [k for k, _ in panels]
