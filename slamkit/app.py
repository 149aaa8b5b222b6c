"""The job behind ``slamkit run``: build the configured components, run SLAM on the dataset, write the run
directory (trajectory.tum, keyframes.tum, metrics.json, config.yaml, trajectory.png)."""

from __future__ import annotations

import csv
import dataclasses
import json
import logging
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

from slamkit.errors import ConfigError, SlamkitError
from slamkit.interfaces import Dataset, MapStore, Optimizer
from slamkit.pipeline.config import PipelineConfig
from slamkit.pipeline.local_mapping import LocalMapper
from slamkit.pipeline.loop_closing import LoopCloser
from slamkit.pipeline.tracking import Tracker, TrackingState
from slamkit.plugins import ComponentRegistry
from slamkit.problems import PoseOnlyProblem, PoseOnlyResult
from slamkit.runtime.log import RunLog
from slamkit.runtime.sequential import SequentialRunner
from slamkit.runtime.threaded import ThreadedRunner
from slamkit.sensors import Trajectory

log = logging.getLogger("slamkit")

RUNNER_KINDS = ("sequential", "threaded")
Runner = SequentialRunner | ThreadedRunner


def build_components(cfg: DictConfig, registry: ComponentRegistry) -> dict[str, Any]:
    """Instantiate every configured component group through the registry (checked against its interface)."""
    built: dict[str, Any] = {}
    from slamkit.optim.factory import build_optimizer

    for kind in ("dataset", "features", "place", "initializer", "optimizer", "map"):
        node = cfg.get(kind)
        if node is None or "_target_" not in node:
            continue
        # the optimizer may run in a worker process (optimizer.worker=process): the factory decides
        built[kind] = build_optimizer(node, registry) if kind == "optimizer" else registry.instantiate(kind, node)
    return built


def _output_dir() -> Path:
    from hydra.core.hydra_config import HydraConfig

    return Path(HydraConfig.get().runtime.output_dir)


def path_length_m(traj: Trajectory) -> float:
    """Sum of the distances between consecutive camera centres, m."""
    if len(traj) < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(traj.positions_m, axis=0), axis=1).sum())


def _percentile(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


#: An accepted loop is false when the true camera centres of its two keyframes are further apart than this, or
#: their optical axes differ by more than FALSE_LOOP_MAX_ANGLE_DEG: they do not see the same place.
FALSE_LOOP_MAX_DISTANCE_M = 2.0
FALSE_LOOP_MAX_ANGLE_DEG = 60.0


def count_false_loops(run: RunLog, store: MapStore, gt: Trajectory | None) -> int | None:
    """Accepted loops whose two keyframes were not truly at the same place (by the ground truth)."""
    if gt is None:
        return None
    false = 0
    for loop in run.loops:
        if loop.loop_kf_id is None:
            continue
        stamps = [loop.kf_id, loop.loop_kf_id]
        times = [store.get_keyframe(k).timestamp_s if store.has_keyframe(k) else None for k in stamps]
        if None in times:
            continue
        idx = [int(np.argmin(np.abs(gt.t_s - t))) for t in times if t is not None]
        a, b = gt.T_w_c[idx[0]], gt.T_w_c[idx[1]]
        dist = float(np.linalg.norm(a[:3, 3] - b[:3, 3]))
        cos = float(np.clip(a[:3, 2] @ b[:3, 2], -1.0, 1.0))
        if dist > FALSE_LOOP_MAX_DISTANCE_M or np.degrees(np.arccos(cos)) > FALSE_LOOP_MAX_ANGLE_DEG:
            false += 1
    return false


def loop_summaries(run: RunLog) -> dict[str, float | int | None]:
    """Scalar summaries of the closed loops (None when no loop closed), for sweep reports:
    ``essential_graph_edges_max`` (edges of the largest essential graph optimized, ORB-SLAM Table VI's "edges"),
    ``essential_graph_ms_total`` (time building and optimizing essential graphs, ms) and
    ``loop_correction_ms_total`` (whole loop corrections: propagation, fusion, essential graph, ms)."""
    closed = [lp for lp in run.loops if lp.loop_kf_id is not None]
    if not closed:
        return {"essential_graph_edges_max": None, "essential_graph_ms_total": None, "loop_correction_ms_total": None}
    return {
        "essential_graph_edges_max": max(lp.essential_graph_edges for lp in closed),
        "essential_graph_ms_total": float(sum(lp.timings_ms.get("essential_graph_ms", 0.0) for lp in closed)),
        "loop_correction_ms_total": float(sum(lp.timings_ms.get("correction_ms", 0.0) for lp in closed)),
    }


def run_metrics(
    run: RunLog, store: MapStore, frames: Trajectory, keyframes: Trajectory, dataset: Dataset
) -> dict[str, Any]:
    """metrics.json of a run: counts, timings, and accuracy against the ground truth when there is one."""
    track_ms = [o.timings_ms["track_ms"] for o in run.tracking if "track_ms" in o.timings_ms]
    extract_ms = [o.timings_ms["extract_ms"] for o in run.tracking if "extract_ms" in o.timings_ms]
    mapping_ms = [sum(m.timings_ms.values()) for m in run.mapping]
    ba_ms = [m.timings_ms.get("local_ba_ms", 0.0) for m in run.mapping]
    states = [o.state for o in run.tracking]
    init_frame = next((o.frame_index for o in run.tracking if o.method == "initialize" and o.state == "ok"), None)
    metrics: dict[str, Any] = {
        "dataset": getattr(dataset, "name", "?"),
        "frames": len(run.tracking),
        # frames with an estimated pose: tracked frames plus the initialisation's reference frame (keyframe 0)
        "frames_tracked": len(frames),
        "frames_lost": int(sum(s == TrackingState.LOST for s in states)),
        "initialized_at_frame": init_frame,
        "resets": run.resets,
        "keyframes": store.n_keyframes(),
        "map_points": store.n_points(),
        "tracking_ms_median": _percentile(track_ms, 50),
        "tracking_ms_p95": _percentile(track_ms, 95),
        "extract_ms_median": _percentile(extract_ms, 50),
        "local_mapping_ms_median": _percentile(mapping_ms, 50),
        "local_ba_ms_median": _percentile(ba_ms, 50),
        "wall_s": run.wall_s,
        "runner": run.runner,
        "frames_dropped": run.frames_dropped,
        "realtime_factor": run.realtime_factor,
        "preloaded_mb": run.preloaded_mb,
        "relocalizations": sum(o.method == "relocalization" and o.state == TrackingState.OK for o in run.tracking),
        "loops_closed": sum(loop.loop_kf_id is not None for loop in run.loops),
        "loop_closing_ms_median": _percentile([sum(lp.timings_ms.values()) for lp in run.loops], 50),
        "essential_graph_edges": [lp.essential_graph_edges for lp in run.loops if lp.loop_kf_id is not None],
        "essential_graph_ms": [
            lp.timings_ms.get("essential_graph_ms") for lp in run.loops if lp.loop_kf_id is not None
        ],
    }
    metrics.update(loop_summaries(run))
    gt = dataset.ground_truth
    if gt is not None and run.tracking:
        # the ground truth over the frames this run processed (max_frames/skip may cut the sequence)
        t0, t1 = run.tracking[0].timestamp_s, run.tracking[-1].timestamp_s
        span = (gt.t_s >= t0 - 1e-6) & (gt.t_s <= t1 + 1e-6)
        gt = Trajectory(gt.t_s[span], gt.T_w_c[span])
    if gt is not None and len(gt) >= 2:
        metrics["path_length_m"] = path_length_m(gt)
        metrics["path_length_source"] = "ground_truth"
        from slamkit.errors import EvaluationError
        from slamkit.eval.metrics import compute_ate

        for name, traj in (("", frames), ("kf_", keyframes)):
            try:
                ate = compute_ate(gt, traj, align="sim3", max_diff_s=0.01)
            except (EvaluationError, SlamkitError) as exc:
                metrics[f"{name}ate_error"] = str(exc)
                continue
            metrics[f"{name}ate_rmse_m"] = ate.rmse_m
            metrics[f"{name}ate_matched_poses"] = ate.matched_poses
            metrics[f"{name}ate_rmse_pct_of_path"] = 100.0 * ate.rmse_m / max(metrics["path_length_m"], 1e-12)
        metrics["ate_align"] = "sim3"
        metrics["loops_false"] = count_false_loops(run, store, dataset.ground_truth)
    else:
        metrics["path_length_m"] = path_length_m(frames)
        metrics["path_length_source"] = "estimate (no ground truth; arbitrary scale for monocular)"
    return metrics


def write_run_logs(out_dir: Path, run: RunLog) -> None:
    """frames.csv: what tracking did with each frame; loops.json: what loop closing did with each keyframe
    (candidates, consistency, BoW matches, Sim3 inliers and scale, corrections), so a user can see why a loop
    was or was not closed."""
    with (out_dir / "frames.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["frame", "timestamp_s", "state", "method", "features", "inliers", "track_ms", "message"])
        for o in run.tracking:
            writer.writerow(
                [
                    o.frame_index,
                    f"{o.timestamp_s:.6f}",
                    o.state.value,
                    o.method,
                    o.n_features,
                    o.inliers,
                    f"{o.timings_ms.get('track_ms', float('nan')):.2f}",
                    o.message,
                ]
            )
    loops = [dataclasses.asdict(lp) for lp in run.loops if lp.candidates or lp.pending or lp.loop_kf_id is not None]
    (out_dir / "loops.json").write_text(json.dumps(loops, indent=2, default=float) + "\n")


def write_outputs(
    out_dir: Path, cfg: DictConfig, runner: Runner, dataset: Dataset, status: str, error: str | None
) -> dict[str, Any]:
    """Write what the run has (also after a failure) and return the metrics."""
    from slamkit.io.trajectory_io import write_trajectory

    out_dir.mkdir(parents=True, exist_ok=True)
    frames = runner.recorder.frames(runner.store)
    keyframes = runner.recorder.keyframes(runner.store)
    write_trajectory(out_dir / "trajectory.tum", frames, "tum")
    write_trajectory(out_dir / "keyframes.tum", keyframes, "tum")
    (out_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    metrics = run_metrics(runner.log, runner.store, frames, keyframes, dataset)
    metrics["status"] = status
    metrics["seed"] = int(cfg.seed)
    if error:
        metrics["error"] = error
    if runner.log.failed_thread is not None:
        metrics["failed_thread"] = runner.log.failed_thread
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2, default=float) + "\n")
    write_run_logs(out_dir, runner.log)
    gt = dataset.ground_truth
    if len(frames) >= 3:
        try:
            from slamkit.eval.metrics import compute_ate
            from slamkit.eval.plot import plot_trajectories

            if gt is not None and len(gt) >= 3:
                ate = compute_ate(gt, frames, align="sim3")
                plot_trajectories(
                    out_dir / "trajectory.png",
                    ate.gt_matched,
                    ate.est_aligned,
                    f"{metrics['dataset']}: ATE {ate.rmse_m:.4f} m (sim3)",
                )
            else:
                plot_trajectories(out_dir / "trajectory.png", None, frames, str(metrics["dataset"]))
        except SlamkitError as exc:
            log.warning("no trajectory plot: %s", exc)
    return metrics


def build_runner(cfg: DictConfig, registry: ComponentRegistry | None = None) -> tuple[Runner, Dataset]:
    """Build the dataset, the components and the runner a composed config describes (no Hydra runtime
    needed: tests and notebooks call this with ``slamkit.config.compose_config(...)``)."""
    registry = registry or ComponentRegistry.discover()
    for failure in registry.failures:
        log.warning("%s", failure)
    components = build_components(cfg, registry)
    dataset: Dataset = components["dataset"]
    pipeline = PipelineConfig.from_node(OmegaConf.to_container(cfg.pipeline, resolve=True))  # type: ignore[arg-type]
    store: MapStore = components["map"]
    rng = np.random.default_rng(int(cfg.seed))
    place = components.get("place")  # None: no relocalization, no loop closing
    init_extractor = None
    factor = pipeline.tracking.init_feature_factor
    if factor != 1 and "n_features" in cfg.features:
        node = {str(k): v for k, v in cfg.features.items()}
        node["n_features"] = round(int(node["n_features"]) * factor)
        init_extractor = registry.instantiate("features", node)
    frontend_node = cfg.get("frontend")
    if frontend_node is None or "_target_" not in frontend_node:
        raise ConfigError("frontend: missing; expected a front end (frontend=mono)")
    frontend = registry.instantiate(
        "frontend", frontend_node, extractor=components["features"], init_extractor=init_extractor
    )
    tracker = Tracker(
        pipeline.tracking,
        frontend,
        components["initializer"],
        components["optimizer"],
        store,
        rng,
        place,
        pose_optimizer=_pose_optimizer(pipeline.tracking.pose_optimization, components["optimizer"]),
    )
    kind = str(cfg.runner.get("kind", "sequential"))
    if kind not in RUNNER_KINDS:
        raise ConfigError(f"runner.kind = {kind!r}: expected one of {', '.join(RUNNER_KINDS)}")
    background_optimizer = components["optimizer"]
    if kind == "threaded":
        background_optimizer = _background_optimizer(cfg, components["optimizer"])
    mapper = LocalMapper(pipeline.local_mapping, store, background_optimizer, place)
    loop_closer = None
    if place is not None:
        loop_closer = LoopCloser(pipeline.loop_closing, store, background_optimizer, place, rng)
    progress = bool(cfg.runner.get("progress", True))
    runner: Runner
    if kind == "threaded":
        runner = ThreadedRunner(
            tracker,
            mapper,
            store,
            progress=progress,
            loop_closer=loop_closer,
            realtime=bool(cfg.runner.get("realtime", False)),
            speed=float(cfg.runner.get("speed", 1.0)),
            preload=bool(cfg.runner.get("preload", False)),
            background_niceness=_int_setting(cfg.runner, "background_niceness", 0, 19, 0),
            gil_switch_interval_s=_switch_interval_s(cfg.runner),
        )
    else:
        runner = SequentialRunner(tracker, mapper, store, progress=progress, loop_closer=loop_closer)
    return runner, dataset


def _int_setting(node: DictConfig, key: str, low: int, high: int, default: int) -> int:
    value = node.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise ConfigError(f"runner.{key} = {value!r}: expected an integer in [{low}, {high}]")
    return int(value)


def _switch_interval_s(node: DictConfig) -> float | None:
    """runner.gil_switch_interval_ms (null: keep the interpreter's) -> seconds."""
    value = node.get("gil_switch_interval_ms", None)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0 < value <= 100:
        raise ConfigError(f"runner.gil_switch_interval_ms = {value!r}: expected a number in (0, 100] ms or null")
    return float(value) / 1e3


def _pose_optimizer(choice: str, optimizer: Optimizer) -> Callable[[PoseOnlyProblem], PoseOnlyResult] | None:
    """Tracking's motion-only BA: None = the tracker's compiled default, or the optimizer backend's."""
    if choice == "compiled":
        return None
    if choice == "optimizer":
        return optimizer.optimize_pose
    raise ConfigError(f"pipeline.tracking.pose_optimization = {choice!r}: expected 'compiled' or 'optimizer'")


def _background_optimizer(cfg: DictConfig, optimizer: Optimizer) -> Optimizer:
    """The optimizer local mapping and loop closing use in the threaded runner: a backend that holds the GIL
    through its C++ calls (GTSAM) would freeze tracking during a local BA, so it runs in a worker process
    (``runner.offload_gil_holding_optimizer``, default true); others run inline."""
    if not getattr(optimizer, "holds_gil", False) or not bool(cfg.runner.get("offload_gil_holding_optimizer", True)):
        return optimizer
    if str(cfg.optimizer.get("worker", "inline")) == "process":
        return optimizer
    from slamkit.optim.factory import build_optimizer

    node = OmegaConf.to_container(cfg.optimizer, resolve=True)
    assert isinstance(node, dict)
    node["worker"] = "process"
    log.info("optimizer %s holds the GIL: local mapping and loop closing use it in a worker process", optimizer.name)
    return build_optimizer({str(k): v for k, v in node.items()})


def _is_multirun() -> bool:
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    return HydraConfig.get().mode == RunMode.MULTIRUN


def write_failed_job(out_dir: Path, cfg: DictConfig, error: str, stage: str) -> dict[str, Any]:
    """metrics.json of a job that failed before it had anything to measure (``stage``: where it failed)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    metrics: dict[str, Any] = {"status": "failed", "stage": stage, "error": error, "seed": cfg.get("seed")}
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2, default=str) + "\n")
    try:
        (out_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    except Exception:  # an unresolvable config may be the very failure: keep it unresolved
        (out_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg))
    return metrics


def run_job(cfg: DictConfig) -> dict[str, Any]:
    """Hydra task function of ``slamkit run``. A failing job writes metrics.json with ``status: failed`` and
    ``error``; in a multirun it then returns (logged as an error) so the other jobs of the sweep go on, in a
    single run it raises."""
    out_dir = _output_dir()
    try:
        runner, dataset = build_runner(cfg)
    except Exception as exc:
        error = "".join(traceback.format_exception_only(type(exc), exc)).strip()
        metrics = write_failed_job(out_dir, cfg, error, "build")
        if not _is_multirun():
            raise
        log.error("job failed while building its components: %s", error)
        return metrics
    log.info("dataset %s: %d frames -> %s", getattr(dataset, "name", "?"), len(dataset), out_dir)
    start = time.perf_counter()
    try:
        runner.run(dataset, dataset.camera)
    except BaseException as exc:
        error = "".join(traceback.format_exception_only(type(exc), exc)).strip()
        status = "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed"
        metrics = write_outputs(out_dir, cfg, runner, dataset, status, error or type(exc).__name__)
        if not isinstance(exc, Exception) or not _is_multirun():
            raise
        log.error("job failed while running: %s", error)
        return metrics
    metrics = write_outputs(out_dir, cfg, runner, dataset, "ok", None)
    log.info(
        "done in %.1f s: %s",
        time.perf_counter() - start,
        json.dumps(
            {k: metrics.get(k) for k in ("frames_tracked", "keyframes", "map_points", "ate_rmse_m", "kf_ate_rmse_m")}
        ),
    )
    print(f"results in {out_dir}")
    return metrics
