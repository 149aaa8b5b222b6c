"""``slamkit bench [OPTIONS] [OVERRIDES...]``: run a sequence and report where the time goes.

Takes the same config overrides as ``slamkit run`` (``slamkit bench +experiment=kitti07 dataset.root=...``).
Reports per-stage timings, median and p95 in ms: tracking (ORB extraction, initial pose = motion model or
reference keyframe or relocalization, local-map tracking, whole frame) over the frames tracked after
initialisation; local mapping per keyframe (whole, and each stage with local BA separately); loop closing
(detection, Sim3, correction, essential graph). Plus frames dropped (real-time playback), the real-time factor
(sequence time / wall time), peak memory (resident set size sampled every 50 ms during the run) and memory per
keyframe, accuracy (ATE) when the dataset has ground truth, and, for runs of 1000+ tracked frames, the median
tracking time of the first and last 500 frames after initialisation (is the cost flat as the map grows?). After the
first 200 frames, cost against map size (slamkit.bench.growth): per quarter of the run the tracking and local-mapping
medians and the keyframes in the map, the last quarter over the first, and memory per keyframe as the slope of
resident memory against keyframes in the map; ``--plot FILE.png`` draws them.

``--runners threaded,sequential`` runs the same config once per runner, one after the other in this process,
and adds the threaded/sequential ATE ratio: the side-by-side comparison of issue 6.
"""

from __future__ import annotations

import argparse
import gc
import json
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import psutil

from slamkit.bench.growth import GrowthProbe, format_growth, growth_report, plot_growth
from slamkit.bench.optimizer import machine_info
from slamkit.errors import ConfigError

__all__ = ["add_bench_run_arguments", "bench_one", "run_bench_command", "summarize_run"]

#: Frames at each end of a long run compared for the flat-cost check (issue 6: first/last 500 after init).
FLAT_COST_WINDOW = 500
_RSS_SAMPLE_S = 0.05
# mapping_wait_ms: frames whose keyframe decision found local mapping busy; playing as fast as possible the
# threaded runner holds tracking there until mapping is free (part of track_ms, shown on its own).
_TRACKING_STAGES = ("extract_ms", "initial_pose_ms", "local_map_ms", "mapping_wait_ms", "track_ms")
# work_ms: track_ms without mapping_wait_ms, the frame's own tracking work. Compares tracking code across versions
# whose keyframe policies make the mapping thread busier or idler (the wait measures local mapping, not tracking).
_TRACKING_WORK_STAGE = "work_ms"
_LOOP_STAGES = ("detect_ms", "sim3_ms", "correction_ms", "essential_graph_ms", "global_ba_ms")


class RssSampler(threading.Thread):
    """Samples this process's resident set size until stopped; ``peak_mb`` is the largest sample."""

    def __init__(self, period_s: float = _RSS_SAMPLE_S) -> None:
        super().__init__(name="rss-sampler", daemon=True)
        self._proc = psutil.Process()
        self._stop_event = threading.Event()
        self.period_s = period_s
        self.start_mb = self._rss_mb()
        self.peak_mb = self.start_mb

    def _rss_mb(self) -> float:
        return float(self._proc.memory_info().rss) / 2**20

    def run(self) -> None:
        while not self._stop_event.wait(self.period_s):
            self.peak_mb = max(self.peak_mb, self._rss_mb())

    def stop(self) -> None:
        self._stop_event.set()
        self.join(timeout=5)
        self.peak_mb = max(self.peak_mb, self._rss_mb())


def _stats(values: Sequence[float]) -> dict[str, float | int | None]:
    if not values:
        return {"median": None, "p95": None, "n": 0}
    arr = np.asarray(values, dtype=np.float64)
    return {"median": float(np.median(arr)), "p95": float(np.percentile(arr, 95)), "n": int(arr.size)}


def _tracking_work_ms(tracked: Sequence[Any]) -> list[float]:
    """Per tracked frame, ms: its tracking time less the time it was held waiting for local mapping."""
    return [
        float(o.timings_ms["track_ms"]) - float(o.timings_ms.get("mapping_wait_ms", 0.0))
        for o in tracked
        if "track_ms" in o.timings_ms
    ]


def summarize_run(
    runner: Any, dataset: Any, peak_rss_mb: float, start_rss_mb: float, probe: GrowthProbe | None = None
) -> dict[str, Any]:
    """The bench record of a finished (or failed) run: stage statistics, counts, memory, accuracy; with ``probe``
    (the run's ``on_frame`` growth probe) the cost against map size (``growth``, see slamkit.bench.growth)."""
    from slamkit.eval.run_metrics import runner_metrics

    log = runner.log
    metrics = runner_metrics(runner, dataset)  # the numbers metrics.json has
    tracked = [o for o in log.tracking if o.state == "ok" and o.method != "initialize"]
    tracking = {s: _stats([o.timings_ms[s] for o in tracked if s in o.timings_ms]) for s in _TRACKING_STAGES}
    tracking[_TRACKING_WORK_STAGE] = _stats(_tracking_work_ms(tracked))
    mapping_stages = sorted({k for m in log.mapping for k in m.timings_ms})
    mapping = {"per_keyframe_ms": _stats(_per_keyframe_ms(log))}
    mapping.update({s: _stats([m.timings_ms[s] for m in log.mapping if s in m.timings_ms]) for s in mapping_stages})
    loops = {s: _stats([lp.timings_ms[s] for lp in log.loops if s in lp.timings_ms]) for s in _LOOP_STAGES}
    n_kf = max(int(metrics["keyframes"]), 1)
    record: dict[str, Any] = {
        "runner": log.runner,
        "dataset": metrics["dataset"],
        "frames": metrics["frames"],
        "frames_tracked": metrics["frames_tracked"],
        "frames_dropped": log.frames_dropped,
        "realtime_factor": log.realtime_factor,
        "wall_s": log.wall_s,
        "keyframes": metrics["keyframes"],
        "keyframes_inserted": len(log.mapping),
        "map_points": metrics["map_points"],
        "loops_closed": metrics["loops_closed"],
        "tracking_ms_median": tracking["track_ms"]["median"],
        "tracking_ms_p95": tracking["track_ms"]["p95"],
        "tracking_work_ms_median": tracking[_TRACKING_WORK_STAGE]["median"],
        "local_mapping_ms_median": mapping["per_keyframe_ms"]["median"],
        "local_ba_ms_median": mapping.get("local_ba_ms", {}).get("median"),
        "local_ba_completed": metrics["local_ba_completed"],
        "peak_rss_mb": peak_rss_mb,
        # frames preloaded before playback (runner.preload) are the dataset's memory, not the map's
        "preloaded_mb": log.preloaded_mb,
        "rss_growth_per_keyframe_mb": (peak_rss_mb - start_rss_mb - log.preloaded_mb) / n_kf,
        "stages": {"tracking": tracking, "local_mapping": mapping, "loop_closing": loops},
    }
    for key in ("ate_rmse_m", "kf_ate_rmse_m", "ate_rmse_pct_of_path", "path_length_m", "loops_false"):
        if key in metrics:
            record[key] = metrics[key]
    overlap = _tracking_beside_local_ba(log)
    if overlap is not None:
        record["tracking_beside_local_ba"] = overlap
    track_ms = [o.timings_ms["track_ms"] for o in tracked if "track_ms" in o.timings_ms]
    if len(track_ms) >= 2 * FLAT_COST_WINDOW:
        first = float(np.median(track_ms[:FLAT_COST_WINDOW]))
        last = float(np.median(track_ms[-FLAT_COST_WINDOW:]))
        record["flat_cost"] = {
            "window_frames": FLAT_COST_WINDOW,
            "first_ms_median": first,
            "last_ms_median": last,
            "last_over_first": last / first if first > 0 else None,
        }
    if probe is not None:
        growth = growth_report(probe.samples, _per_keyframe_ms(log))
        if growth is not None:
            record["growth"] = growth
    return record


def _per_keyframe_ms(log: Any) -> list[float]:
    """Local mapping's time per keyframe (all stages), ms, in the order the keyframes were processed."""
    return [float(sum(m.timings_ms.values())) for m in log.mapping]


def _tracking_beside_local_ba(log: Any) -> dict[str, Any] | None:
    """Median wall time of tracking a frame while a local BA ran in the mapping thread, and otherwise (threaded
    runner only): a backend that holds the GIL shows up as a large ratio."""
    if not log.tracking_wall_s or not log.local_ba_wall_s:
        return None
    ba = np.asarray(log.local_ba_wall_s, dtype=np.float64)
    during: list[float] = []
    apart: list[float] = []
    for out, (t0, t1) in zip(log.tracking, log.tracking_wall_s, strict=False):
        if out.state != "ok" or out.method == "initialize":
            continue
        overlaps = bool(np.any((ba[:, 0] < t1) & (ba[:, 1] > t0)))
        (during if overlaps else apart).append((t1 - t0) * 1e3)
    med_during = float(np.median(during)) if during else None
    med_apart = float(np.median(apart)) if apart else None
    return {
        "frames_during_ba": len(during),
        "frames_otherwise": len(apart),
        "tracking_ms_median_during_ba": med_during,
        "tracking_ms_median_otherwise": med_apart,
        "ratio": med_during / med_apart if med_during is not None and med_apart else None,
    }


def compose_bench_config(overrides: Sequence[str], progress: bool = True) -> Any:
    """The composed config of one bench run; ConfigError naming the overrides when Hydra cannot compose it."""
    from hydra.errors import HydraException

    from slamkit.config import compose_config

    try:
        return compose_config([*overrides, f"runner.progress={'true' if progress else 'false'}"])
    except HydraException as exc:
        raise ConfigError(f"slamkit bench: cannot compose the config for {' '.join(overrides)}: {exc}") from None


def bench_one(overrides: Sequence[str], progress: bool = True, plot: Path | None = None) -> dict[str, Any]:
    """Compose the config from ``overrides``, run it, and return the bench record (``status`` ok/failed); ``plot``:
    a PNG to draw the cost against map size into (slamkit.bench.growth.plot_growth)."""
    from slamkit.app import build_runner

    cfg = compose_bench_config(overrides, progress)
    runner, dataset = build_runner(cfg)
    probe = GrowthProbe(runner)
    prepare = getattr(dataset, "prepare_playback", None)
    if callable(prepare):
        # the dataset's one-off memory (the synthetic world's textures, made lazily as walls come into view
        # otherwise) is not the map's: made before the memory baseline, so memory per keyframe is the map's
        prepare()
    gc.collect()
    sampler = RssSampler()
    sampler.start()
    status, error = "ok", None
    from omegaconf import OmegaConf

    config = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(config, dict)
    try:
        # the composed config goes to the lifecycle hooks as in `slamkit run` (a listener such as the viewer reads
        # its settings there); no run directory: a bench writes no run outputs
        runner.run(dataset, dataset.camera, on_frame=probe, config={str(k): v for k, v in config.items()})
    except Exception as exc:  # a failed run still reports what it measured
        status, error = "failed", f"{type(exc).__name__}: {exc}"
    finally:
        sampler.stop()
    record = summarize_run(runner, dataset, sampler.peak_mb, sampler.start_mb, probe)
    if plot is not None:
        title = f"{record['runner']}: {' '.join(overrides) or '(defaults)'}"
        record["plot"] = str(plot_growth(plot, probe.samples, _per_keyframe_ms(runner.log), title=title))
    record["status"] = status
    record["overrides"] = list(overrides)
    if error:
        record["error"] = error.splitlines()[0]
    return record


def _fmt(value: Any, digits: int = 1) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def format_table(records: Sequence[dict[str, Any]]) -> str:
    """A plain-text table: one column pair (median / p95) per run."""
    header = ["stage (ms)"] + [f"{r['runner']} median / p95" for r in records]
    rows: list[list[str]] = []
    groups = ("tracking", "local_mapping", "loop_closing")
    names = sorted(
        {(g, s) for r in records for g in groups for s in r["stages"][g]}, key=lambda gs: groups.index(gs[0])
    )
    for group, stage in names:
        cells = []
        for r in records:
            st = r["stages"][group].get(stage)
            cells.append("-" if not st or st["n"] == 0 else f"{_fmt(st['median'])} / {_fmt(st['p95'])}  (n={st['n']})")
        rows.append([f"{group}.{stage}", *cells])
    for key, digits in (
        ("frames", 0),
        ("frames_tracked", 0),
        ("frames_dropped", 0),
        ("realtime_factor", 2),
        ("wall_s", 1),
        ("keyframes", 0),
        ("map_points", 0),
        ("loops_closed", 0),
        ("peak_rss_mb", 0),
        ("preloaded_mb", 0),
        ("rss_growth_per_keyframe_mb", 3),
        ("ate_rmse_m", 4),
        ("kf_ate_rmse_m", 4),
        ("ate_rmse_pct_of_path", 3),
        ("status", 0),
    ):
        rows.append([key, *[_fmt(r.get(key), digits) for r in records]])
    optional_rows = (
        (
            "tracking during / apart from local BA (ms)",
            "tracking_beside_local_ba",
            lambda x: f"{_fmt(x['tracking_ms_median_during_ba'])} / {_fmt(x['tracking_ms_median_otherwise'])}",
        ),
        (
            "local BA completed / due (skipped, aborted)",
            "local_ba_completed",
            lambda x: (
                f"{x['completed']} / {x['due']} ({x['skipped']}, {x['aborted']})"
                + ("" if x["fraction"] is None else f" = {100 * x['fraction']:.0f}%")
            ),
        ),
        (
            "tracking first/last 500 (ms)",
            "flat_cost",
            lambda x: f"{_fmt(x['first_ms_median'])} / {_fmt(x['last_ms_median'])} (x{_fmt(x['last_over_first'], 2)})",
        ),
    )
    for label, key, cell in optional_rows:
        if any(key in r for r in records):
            rows.append([label, *[cell(r[key]) if key in r else "-" for r in records]])
    widths = [max(len(row[i]) for row in [header, *rows]) for i in range(len(header))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(header, widths, strict=True))]
    lines.append("  ".join("-" * w for w in widths))
    lines += ["  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)) for row in rows]
    return "\n".join(lines)


def add_bench_run_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("overrides", nargs="*", help="config overrides, as for `slamkit run` (key=value, +group=x)")
    parser.add_argument("--json", type=Path, default=None, help="write every figure to this JSON file")
    parser.add_argument(
        "--runners",
        default=None,
        help="comma-separated runners to run side by side on the same config (e.g. threaded,sequential); "
        "default: the config's runner",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument(
        "--plot",
        type=Path,
        default=None,
        help="draw tracking, local mapping and memory against keyframes in the map into this PNG (one file per "
        "runner: FILE_<runner>.png when several are run)",
    )


def run_bench_command(args: argparse.Namespace) -> int:
    runners = [r.strip() for r in args.runners.split(",")] if args.runners else [None]
    records = []
    plans = [list(args.overrides) + ([f"runner={kind}"] if kind else []) for kind in runners]
    for overrides in plans:  # every config composes before anything runs: a typo must not cost the first run
        compose_bench_config(overrides)
    if args.plot is not None and args.plot.suffix.lower() != ".png":
        raise ConfigError(f"slamkit bench --plot: {args.plot} must end in .png")
    for kind, overrides in zip(runners, plans, strict=True):
        print(f"slamkit bench: {' '.join(overrides) or '(defaults)'}", file=sys.stderr)
        plot = args.plot
        if plot is not None and len(plans) > 1:
            plot = plot.with_name(f"{plot.stem}_{kind}{plot.suffix}")
        t0 = time.perf_counter()
        records.append(bench_one(overrides, progress=not args.no_progress, plot=plot))
        print(f"  done in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    result: dict[str, Any] = {
        "machine": machine_info(),
        "date_utc": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "load_average_1min": psutil.getloadavg()[0],
        "runs": records,
    }
    # the first run's headline figures at top level (the keys issue 6 asks for)
    for key in ("tracking_ms_median", "local_mapping_ms_median", "frames_dropped", "realtime_factor", "peak_rss_mb"):
        result[key] = records[0].get(key)
    by_runner = {r["runner"]: r for r in records}
    if "threaded" in by_runner and "sequential" in by_runner:
        t, s = by_runner["threaded"].get("ate_rmse_m"), by_runner["sequential"].get("ate_rmse_m")
        result["ate_ratio_threaded_over_sequential"] = t / s if t is not None and s else None
    print(format_table(records))
    for r in records:
        if "growth" in r:
            print(f"{r['runner']}: {format_growth(r['growth'])}")
    if "ate_ratio_threaded_over_sequential" in result:
        print(f"ATE threaded / sequential: {_fmt(result['ate_ratio_threaded_over_sequential'], 2)}")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2, default=float) + "\n")
        print(f"wrote {args.json}", file=sys.stderr)
    return 0 if all(r["status"] == "ok" for r in records) else 1
