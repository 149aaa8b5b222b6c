"""Cost as the map grows (issue 15 item 4): tracking per frame, local mapping per keyframe and memory, against the
number of keyframes in the map.

A :class:`GrowthProbe` is the runner's ``on_frame`` callback: after each frame it notes the keyframes in the Atlas
(every map), how many keyframes local mapping has processed so far, the process's resident set size and the frame's
tracking time. :func:`growth_report` cuts the run after its first ``skip_frames`` frames into ``parts`` equal runs of
frames (quarters by default) and gives, per part, the tracking median over its tracked frames, the local-mapping
median over the keyframes processed during it, and the map size and memory at its end; then the last part's medians
over the first part's, and the memory per keyframe as the slope of a straight line fitted to resident memory against
keyframes in the map (MiB per keyframe: what each keyframe added costs, without the fixed cost of the process, the
vocabulary and the compiled kernels that a peak-over-count figure divides in). :func:`plot_growth` draws the three
against the map size.

Both runners call ``on_frame`` from the thread that tracks; the counts read there are single reads of a dict's size
(no lock needed). In the threaded runner a keyframe's local mapping may end a few frames after it was made, so a
part's keyframes are those whose processing had ended by its last frame.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import psutil

from slamkit.errors import ConfigError

__all__ = ["GrowthProbe", "GrowthSample", "growth_report", "plot_growth"]

#: Frames left out at the start of a run (issue 15: "after the first 200 frames"): initialisation and the first
#: keyframes, whose costs are not those of a map that has grown.
SKIP_FRAMES = 200
#: Parts the rest of the run is cut into (issue 15: the first and last quarter are compared).
PARTS = 4


@dataclass(frozen=True)
class GrowthSample:
    """One frame's note. keyframes: keyframes in the Atlas after the frame; mapped: keyframes local mapping had
    processed by then (the length of the run log's ``mapping``); rss_mb: resident set size, MiB; track_ms: the
    frame's tracking time (None when it was not tracked by the motion model, reference keyframe or
    relocalization: initialisation attempts and lost frames are not the per-frame cost)."""

    frame_index: int
    keyframes: int
    mapped: int
    rss_mb: float
    track_ms: float | None


class GrowthProbe:
    """The runner's ``on_frame`` callback that records a :class:`GrowthSample` per frame (``samples``)."""

    def __init__(self, runner: Any) -> None:
        self._runner = runner
        self._proc = psutil.Process()
        self.samples: list[GrowthSample] = []

    def _keyframes(self) -> int:
        atlas = self._runner.atlas
        return int(sum(atlas.get(m).n_keyframes() for m in atlas.map_ids()))

    def __call__(self, out: Any) -> None:
        tracked = out.state == "ok" and out.method != "initialize" and "track_ms" in out.timings_ms
        self.samples.append(
            GrowthSample(
                frame_index=int(out.frame_index),
                keyframes=self._keyframes(),
                mapped=len(self._runner.log.mapping),
                rss_mb=float(self._proc.memory_info().rss) / 2**20,
                track_ms=float(out.timings_ms["track_ms"]) if tracked else None,
            )
        )


def _median(values: list[float]) -> float | None:
    return float(np.median(values)) if values else None


def _ratio(last: float | None, first: float | None) -> float | None:
    return last / first if last is not None and first else None


def growth_report(
    samples: list[GrowthSample],
    mapping_ms: list[float],
    skip_frames: int = SKIP_FRAMES,
    parts: int = PARTS,
) -> dict[str, Any] | None:
    """The growth record of a run (see the module docstring), or None when fewer than ``parts`` frames follow the
    first ``skip_frames``.

    samples: the probe's, in frame order. mapping_ms: local mapping's time per keyframe, ms, in the order the
    keyframes were processed (index j is the keyframe counted by ``GrowthSample.mapped > j``).
    Returns {"skip_frames", "parts": [{"frames": [first, last], "keyframes_at_end", "rss_mb_at_end",
    "tracking_ms_median", "tracked_frames", "local_mapping_ms_median", "keyframes_mapped"}, ...],
    "tracking_last_over_first", "local_mapping_last_over_first", "keyframes_max", "rss_mb_per_keyframe"}.
    """
    rest = samples[skip_frames:]
    if len(rest) < parts:
        return None
    bounds = np.linspace(0, len(rest), parts + 1).round().astype(int)
    mapped_before = samples[skip_frames - 1].mapped if skip_frames > 0 and len(samples) >= skip_frames else 0
    out_parts: list[dict[str, Any]] = []
    for a, b in itertools.pairwise(bounds):
        chunk = rest[a:b]
        track = [s.track_ms for s in chunk if s.track_ms is not None]
        mapped_end = chunk[-1].mapped
        kf_ms = mapping_ms[mapped_before:mapped_end]
        out_parts.append(
            {
                "frames": [chunk[0].frame_index, chunk[-1].frame_index],
                "keyframes_at_end": chunk[-1].keyframes,
                "rss_mb_at_end": chunk[-1].rss_mb,
                "tracking_ms_median": _median(track),
                "tracked_frames": len(track),
                "local_mapping_ms_median": _median(kf_ms),
                "keyframes_mapped": len(kf_ms),
            }
        )
        mapped_before = mapped_end
    kf = np.array([s.keyframes for s in rest], dtype=np.float64)
    rss = np.array([s.rss_mb for s in rest], dtype=np.float64)
    # least-squares slope of memory against map size; undefined when the map did not grow
    slope = float(np.polyfit(kf, rss, 1)[0]) if np.ptp(kf) > 0 else None
    first, last = out_parts[0], out_parts[-1]
    return {
        "skip_frames": skip_frames,
        "parts": out_parts,
        "tracking_last_over_first": _ratio(last["tracking_ms_median"], first["tracking_ms_median"]),
        "local_mapping_last_over_first": _ratio(last["local_mapping_ms_median"], first["local_mapping_ms_median"]),
        "keyframes_max": int(kf.max()),
        "rss_mb_per_keyframe": slope,
    }


def format_growth(report: dict[str, Any]) -> str:
    """The growth record as a plain-text table, one row per part, then the ratios and the memory slope."""

    def f(v: Any, digits: int = 1) -> str:
        return "-" if v is None else (f"{v:.{digits}f}" if isinstance(v, float) else str(v))

    header = ["frames", "KF in map (end)", "tracking median ms (n)", "local mapping median ms/KF (n)", "RSS MiB (end)"]
    rows = [
        [
            f"{p['frames'][0]}-{p['frames'][1]}",
            str(p["keyframes_at_end"]),
            f"{f(p['tracking_ms_median'])} ({p['tracked_frames']})",
            f"{f(p['local_mapping_ms_median'])} ({p['keyframes_mapped']})",
            f(p["rss_mb_at_end"], 0),
        ]
        for p in report["parts"]
    ]
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    lines = [f"cost as the map grows (after the first {report['skip_frames']} frames):"]
    lines += ["  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)) for row in [header, *rows]]
    lines.append(
        f"last / first part: tracking x{f(report['tracking_last_over_first'], 2)}, local mapping "
        f"x{f(report['local_mapping_last_over_first'], 2)}; memory {f(report['rss_mb_per_keyframe'], 3)} MiB per "
        f"keyframe (slope over {report['keyframes_max']} keyframes at most)"
    )
    return "\n".join(lines)


def plot_growth(
    path: str | Path, samples: list[GrowthSample], mapping_ms: list[float], title: str = "", dpi: int = 110
) -> Path:
    """A PNG of three panels against keyframes in the map: tracking time per frame, local mapping time per keyframe
    (ms; dots, with a running median), resident memory (MiB). Raises ConfigError unless ``path`` ends in .png."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ConfigError(f"slamkit bench --plot: {path} must end in .png")
    kf = np.array([s.keyframes for s in samples], dtype=np.float64)
    fig = Figure(figsize=(13.0, 4.2), dpi=dpi)
    FigureCanvasAgg(fig)
    tracked = [(s.keyframes, s.track_ms) for s in samples if s.track_ms is not None]
    # the map size when each keyframe's local mapping had ended: the first frame whose count includes it
    mapped = np.array([s.mapped for s in samples])
    kf_of_mapping = [kf[min(int(np.searchsorted(mapped, j + 1)), len(kf) - 1)] for j in range(len(mapping_ms))]
    panels = (
        ("tracking per frame [ms]", [t[0] for t in tracked], [t[1] for t in tracked]),
        ("local mapping per keyframe [ms]", kf_of_mapping, list(mapping_ms)),
        ("resident memory [MiB]", list(kf), [s.rss_mb for s in samples]),
    )
    for k, (label, x, y) in enumerate(panels):
        ax = fig.add_subplot(1, 3, k + 1)
        ax.plot(x, y, ".", ms=2.0, alpha=0.4, color="tab:blue")
        if k < 2 and len(y) >= 25:
            window = 25
            running = [float(np.median(y[max(0, i - window) : i + 1])) for i in range(len(y))]
            ax.plot(x, running, "-", color="tab:red", lw=1.2, label=f"running median ({window})")
            ax.legend(loc="upper left", fontsize="small")
        ax.set_xlabel("keyframes in the map")
        ax.set_ylabel(label)
        ax.grid(True, lw=0.3)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, format="png")
    return path
