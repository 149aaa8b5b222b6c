"""The metrics of a run (metrics.json): counts, timings, and accuracy against the ground truth when there is one.

One function, :func:`run_metrics`, computes them for the run's outputs (from the run's lifecycle events,
slamkit/eval/outputs.py), for ``slamkit bench`` and for tests (from a runner's own ``RunLog``): both accounts of a
run have the same shape (:class:`RunAccount`), so the numbers agree.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Protocol

import numpy as np

from slamkit.errors import EvaluationError, SlamkitError
from slamkit.events import MapSnapshot
from slamkit.sensors import Trajectory

#: An accepted loop is false when the true camera centres of its two keyframes are further apart than this, or
#: their optical axes differ by more than FALSE_LOOP_MAX_ANGLE_DEG: they do not see the same place.
FALSE_LOOP_MAX_DISTANCE_M = 2.0
FALSE_LOOP_MAX_ANGLE_DEG = 60.0


class FrameAccount(Protocol):
    """What tracking did with one frame (a ``TrackingOutcome`` or a ``FrameTracked`` event)."""

    @property
    def frame_index(self) -> int: ...
    @property
    def timestamp_s(self) -> float: ...
    @property
    def state(self) -> str: ...
    @property
    def method(self) -> str: ...
    @property
    def timings_ms(self) -> Mapping[str, float]: ...


class KeyFrameAccount(Protocol):
    """What local mapping did with one keyframe (a ``MappingOutcome`` or a ``KeyFrameInserted`` event)."""

    @property
    def timings_ms(self) -> Mapping[str, float]: ...
    @property
    def ba_due(self) -> bool: ...
    @property
    def ba_skipped(self) -> bool: ...
    @property
    def ba_aborted(self) -> bool: ...


class LoopAccount(Protocol):
    """What loop closing did with one keyframe (a ``LoopOutcome`` or a ``LoopChecked`` event)."""

    @property
    def kf_id(self) -> int: ...
    @property
    def loop_kf_id(self) -> int | None: ...
    @property
    def essential_graph_edges(self) -> int: ...
    @property
    def timings_ms(self) -> Mapping[str, float]: ...


class RunAccount(Protocol):
    """A run's account: one record per frame tracked, per keyframe mapped, per keyframe loop closing processed,
    and the run's totals (``slamkit.runtime.log.RunLog``, or ``slamkit.eval.run_record.RunRecord`` rebuilt from
    the lifecycle events)."""

    @property
    def tracking(self) -> Sequence[FrameAccount]: ...
    @property
    def mapping(self) -> Sequence[KeyFrameAccount]: ...
    @property
    def loops(self) -> Sequence[LoopAccount]: ...
    @property
    def resets(self) -> int: ...
    @property
    def maps_merged(self) -> int: ...
    @property
    def wall_s(self) -> float: ...
    @property
    def runner(self) -> str: ...
    @property
    def frames_dropped(self) -> int: ...
    @property
    def frames_skipped(self) -> int: ...
    @property
    def realtime_factor(self) -> float | None: ...
    @property
    def source_end(self) -> str | None: ...
    @property
    def preloaded_mb(self) -> float: ...


def path_length_m(traj: Trajectory) -> float:
    """Sum of the distances between consecutive camera centres, m."""
    if len(traj) < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(traj.positions_m, axis=0), axis=1).sum())


def local_ba_completed(mapping: Sequence[KeyFrameAccount]) -> dict[str, Any]:
    """Of the keyframes local mapping processed that were due a local BA (``MappingOutcome.ba_due``): how many ran
    it to the end, how many skipped it (a newer keyframe's abort before it started) and how many stopped it early;
    ``fraction`` completed / due (None when none was due). Issue 15's real-time bar: at least 0.8."""
    due = [m for m in mapping if m.ba_due]
    skipped = sum(m.ba_skipped for m in due)
    aborted = sum(m.ba_aborted for m in due)
    completed = len(due) - skipped - aborted
    return {
        "due": len(due),
        "completed": completed,
        "skipped": skipped,
        "aborted": aborted,
        "fraction": completed / len(due) if due else None,
    }


def _percentile(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


def count_false_loops(run: RunAccount, keyframe_timestamps_s: Mapping[int, float], gt: Trajectory | None) -> int | None:
    """Accepted loops whose two keyframes were not truly at the same place (by the ground truth).

    keyframe_timestamps_s: kf_id -> timestamp (s) of the keyframes in the map at the end (a loop with a culled
    keyframe is not judged)."""
    if gt is None:
        return None
    false = 0
    for loop in run.loops:
        if loop.loop_kf_id is None:
            continue
        times = [keyframe_timestamps_s.get(k) for k in (loop.kf_id, loop.loop_kf_id)]
        if None in times:
            continue
        idx = [int(np.argmin(np.abs(gt.t_s - t))) for t in times if t is not None]
        a, b = gt.T_w_c[idx[0]], gt.T_w_c[idx[1]]
        dist = float(np.linalg.norm(a[:3, 3] - b[:3, 3]))
        cos = float(np.clip(a[:3, 2] @ b[:3, 2], -1.0, 1.0))
        if dist > FALSE_LOOP_MAX_DISTANCE_M or np.degrees(np.arccos(cos)) > FALSE_LOOP_MAX_ANGLE_DEG:
            false += 1
    return false


def loop_summaries(run: RunAccount) -> dict[str, float | int | None]:
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
    run: RunAccount,
    final_map: MapSnapshot,
    frames: Trajectory,
    keyframes: Trajectory,
    dataset_name: str,
    ground_truth: Trajectory | None,
    all_maps: Sequence[MapSnapshot] = (),
) -> dict[str, Any]:
    """metrics.json of a run: counts, timings, and accuracy against the ground truth when there is one.

    final_map: the run's map (keyframe and point counts; with several maps in the Atlas the one whose trajectory
    ``frames`` is, the biggest). frames / keyframes: the estimated trajectories, T_w_c per timestamp.
    all_maps: every map of the Atlas (their keyframe times judge the loops closed in each; default: final_map).
    """
    track_ms = [o.timings_ms["track_ms"] for o in run.tracking if "track_ms" in o.timings_ms]
    extract_ms = [o.timings_ms["extract_ms"] for o in run.tracking if "extract_ms" in o.timings_ms]
    mapping_ms = [sum(m.timings_ms.values()) for m in run.mapping]
    ba_ms = [m.timings_ms.get("local_ba_ms", 0.0) for m in run.mapping]
    ba_completed = local_ba_completed(run.mapping)
    states = [o.state for o in run.tracking]
    init_frame = next((o.frame_index for o in run.tracking if o.method == "initialize" and o.state == "ok"), None)
    metrics: dict[str, Any] = {
        "dataset": dataset_name,
        "frames": len(run.tracking),
        # frames with an estimated pose: tracked frames plus a monocular initialisation's reference frame (keyframe 0)
        "frames_tracked": len(frames),
        "frames_lost": int(sum(s == "lost" for s in states)),
        "initialized_at_frame": init_frame,
        "resets": run.resets,
        # keyframes local mapping inserted during the run (0 in localization mode), culled ones included; a loaded
        # map's keyframes are not added by the run
        "keyframes_added": len(run.mapping),
        "maps_merged": run.maps_merged,  # ORB-SLAM3 map merging: counted from the run's MapsMerged events
        "keyframes": final_map.n_keyframes,
        "map_points": final_map.n_points,
        "tracking_ms_median": _percentile(track_ms, 50),
        "tracking_ms_p95": _percentile(track_ms, 95),
        "extract_ms_median": _percentile(extract_ms, 50),
        "local_mapping_ms_median": _percentile(mapping_ms, 50),
        "local_ba_ms_median": _percentile(ba_ms, 50),
        # keyframes whose local BA ran to the end, of those due one (a newer keyframe's abort skips or stops it)
        "local_ba_completed": ba_completed,
        "local_ba_completed_fraction": ba_completed["fraction"],  # the same as a scalar, for sweeps
        "wall_s": run.wall_s,
        "runner": run.runner,
        "frames_dropped": run.frames_dropped,
        "frames_skipped": run.frames_skipped,
        "realtime_factor": run.realtime_factor,
        "stream_end": run.source_end,  # a live source (dataset=camera): how its stream ended; null otherwise
        "preloaded_mb": run.preloaded_mb,
        "relocalizations": sum(o.method == "relocalization" and o.state == "ok" for o in run.tracking),
        "loops_closed": sum(loop.loop_kf_id is not None for loop in run.loops),
        "loop_closing_ms_median": _percentile([sum(lp.timings_ms.values()) for lp in run.loops], 50),
        "essential_graph_edges": [lp.essential_graph_edges for lp in run.loops if lp.loop_kf_id is not None],
        "essential_graph_ms": [
            lp.timings_ms.get("essential_graph_ms") for lp in run.loops if lp.loop_kf_id is not None
        ],
    }
    metrics.update(loop_summaries(run))
    gt = ground_truth
    if gt is not None and run.tracking:
        # the ground truth over the frames this run processed (max_frames/skip may cut the sequence)
        t0, t1 = run.tracking[0].timestamp_s, run.tracking[-1].timestamp_s
        span = (gt.t_s >= t0 - 1e-6) & (gt.t_s <= t1 + 1e-6)
        gt = Trajectory(gt.t_s[span], gt.T_w_c[span])
    if gt is not None and len(gt) >= 2:
        metrics["path_length_m"] = path_length_m(gt)
        metrics["path_length_source"] = "ground_truth"
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
            # SE(3) alignment (no scale): the figure of a stereo/RGB-D run, whose scale is part of the estimate
            se3 = compute_ate(gt, traj, align="se3", max_diff_s=0.01)
            metrics[f"{name}ate_se3_rmse_m"] = se3.rmse_m
        metrics["ate_align"] = "sim3"
        times = {k: t for m in (all_maps or (final_map,)) for k, t in m.keyframe_timestamps().items()}
        metrics["loops_false"] = count_false_loops(run, times, ground_truth)
    else:
        metrics["path_length_m"] = path_length_m(frames)
        metrics["path_length_source"] = "estimate (no ground truth; arbitrary scale for monocular)"
    return metrics


def map_metrics(
    snapshot: MapSnapshot, frames: Trajectory, keyframes: Trajectory, ground_truth: Trajectory | None
) -> dict[str, Any]:
    """One entry of metrics.json's ``maps``: a map of the Atlas with its frames and keyframes (T_w_c), and the
    accuracy of each against the ground truth after a Sim3 alignment of that map alone (each map has its own
    frame and, monocular, its own scale). ``ate_rmse_m`` / ``kf_ate_rmse_m`` are null with the reason in
    ``ate_error`` / ``kf_ate_error`` when there is no ground truth or too few poses to align."""
    entry: dict[str, Any] = {
        "id": snapshot.map_id,
        "frames": len(frames),
        "keyframes": snapshot.n_keyframes,
        "points": snapshot.n_points,
    }
    from slamkit.eval.metrics import compute_ate

    for name, traj in (("", frames), ("kf_", keyframes)):
        entry[f"{name}ate_rmse_m"] = None
        if ground_truth is None:
            entry[f"{name}ate_error"] = "no ground truth"
            continue
        try:
            ate = compute_ate(ground_truth, traj, align="sim3", max_diff_s=0.01)
        except (EvaluationError, SlamkitError) as exc:
            entry[f"{name}ate_error"] = str(exc)
            continue
        entry[f"{name}ate_rmse_m"] = ate.rmse_m
        entry[f"{name}ate_matched_poses"] = ate.matched_poses
    return entry


class InProcessRun(Protocol):
    """A runner driven in-process (tests, ``slamkit bench``): its own account of the run, trajectory and maps."""

    @property
    def log(self) -> RunAccount: ...
    @property
    def recorder(self) -> Any: ...
    @property
    def store(self) -> Any: ...
    @property
    def atlas(self) -> Any: ...


def runner_metrics(runner: InProcessRun, dataset: Any) -> dict[str, Any]:
    """:func:`run_metrics` of a runner that ran in this process, from its ``RunLog``, trajectory recorder and
    active map: the numbers its metrics.json has when the run kept one map (the outputs plugin computes them from
    the lifecycle events, for every map of the Atlas; a runner's recorder holds the active map's frames only, so
    here ``maps`` lists the active map alone)."""
    store = runner.store
    snapshot = MapSnapshot.of_store(store, int(runner.atlas.active_id))
    frames, keyframes = runner.recorder.frames(store), runner.recorder.keyframes(store)
    gt = dataset.ground_truth
    metrics = run_metrics(runner.log, snapshot, frames, keyframes, str(getattr(dataset, "name", "?")), gt)
    metrics["maps"] = [map_metrics(snapshot, frames, keyframes, gt)]
    return metrics
