"""Plot an aligned estimate over its ground truth into a PNG (matplotlib Agg canvas, no pyplot state)."""

from __future__ import annotations

from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from slamkit.errors import ConfigError
from slamkit.sensors import Trajectory


def plot_trajectories(
    path: str | Path,
    gt: Trajectory | None,
    est_aligned: Trajectory,
    title: str = "",
    dpi: int = 120,
) -> Path:
    """Write a PNG with two panels, top view (x-y) and side view (x-z), of the camera centres in metres.

    gt: the ground truth (world frame); est_aligned: the estimate already aligned into that world frame
    (e.g. ``apply_sim3(ate.alignment, est)``). Without ground truth only the estimate is drawn.
    Returns the path written.
    """
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ConfigError(f"plot path {path} must end in .png")
    fig = Figure(figsize=(12.0, 5.5), dpi=dpi)
    FigureCanvasAgg(fig)
    p_est = est_aligned.positions_m
    for k, (j, label) in enumerate(((1, "y"), (2, "z"))):
        ax = fig.add_subplot(1, 2, k + 1)
        if gt is not None:
            ax.plot(gt.positions_m[:, 0], gt.positions_m[:, j], "-", color="0.35", lw=1.2, label="ground truth")
        est_label = "estimate (aligned)" if gt is not None else "estimate"
        ax.plot(p_est[:, 0], p_est[:, j], ".-", color="tab:blue", lw=1.0, ms=2.5, label=est_label)
        ax.plot(p_est[:1, 0], p_est[:1, j], "o", color="tab:green", ms=5, label="estimate start")
        ax.set_xlabel("x [m]")
        ax.set_ylabel(f"{label} [m]")
        ax.set_title(f"x-{label} ({'top' if label == 'y' else 'side'} view)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, lw=0.3)
        ax.legend(loc="best", fontsize="small")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, format="png")
    return path
