"""The run's own outputs, written by a built-in plugin on the lifecycle hooks (entry point ``outputs`` of the
``slamkit`` group, like every other plugin).

For a run with a run directory (``RunStarted.run_dir``; ``slamkit run`` gives Hydra's output directory), it keeps
the run's account from its events (slamkit/eval/run_record.py) and, at ``slamkit_run_finished`` (also after a
failure or Ctrl-C: a run that fails late keeps what it has), writes:

- trajectory.tum: every frame with an estimated pose, T_w_c (TUM: t x y z qx qy qz qw), in the run's main map:
  the map of the Atlas with the most keyframes (ORB-SLAM3 SaveTrajectoryEuRoC), the only one in most runs; in a
  run on a loaded map file (``map.load``, multi-session) with the frames of the earlier sessions the file kept for
  that map too, in timestamp order, all placed against the keyframes as this run leaves them (one trajectory in one
  frame); metrics.json's frame counts and ATE are of this run's frames;
- keyframes.tum: that map's keyframes;
- maps/<id>/trajectory.tum, maps/<id>/keyframes.tum, maps/<id>/frames.csv: the same for each map of the Atlas
  (frames.csv: the frames tracking handled while that map was active);
- config.yaml: the run's resolved config;
- metrics.json: :func:`slamkit.eval.run_metrics.run_metrics` plus ``status``, ``seed`` (and ``error``,
  ``failed_thread`` when it failed), and ``maps``: one :func:`slamkit.eval.run_metrics.map_metrics` entry per map;
- frames.csv: what tracking did with each frame (and the frames skipped or, in real-time playback, dropped); loops.json: what loop closing did with each keyframe that had
  loop candidates or a pending hypothesis (why a loop was or was not closed);
- trajectory.png: the trajectory aligned to the ground truth (Sim3) when there is one.

It is the run's *critical* listener (:data:`PLUGIN_NAME`): if it fails the run fails, where any other listener's
failure is only logged.
"""

from __future__ import annotations

import csv
import json
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from slamkit.errors import SlamkitError
from slamkit.events import (
    FrameSkipped,
    FrameTracked,
    KeyFrameCulled,
    KeyFrameInserted,
    LoopChecked,
    MapCreated,
    MapsMerged,
    RunFinished,
    RunStarted,
)
from slamkit.hookspecs import hookimpl

if TYPE_CHECKING:  # loaded with the first run: plugin discovery (every `slamkit` command) stays light
    from slamkit.eval.run_record import RunRecord

log = logging.getLogger("slamkit")

#: The name this plugin registers under (pyproject.toml ``[project.entry-points.slamkit]``).
PLUGIN_NAME = "outputs"


class RunOutputs:
    """The plugin: one :class:`RunRecord` per run that has a run directory, written when it finishes."""

    def __init__(self) -> None:
        self._runs: dict[int, RunRecord] = {}

    @hookimpl
    def slamkit_run_started(self, event: RunStarted) -> None:
        if event.run_dir is not None:
            from slamkit.eval.run_record import RunRecord

            self._runs[event.run_id] = RunRecord(event)

    @hookimpl
    def slamkit_map_created(self, event: MapCreated) -> None:
        record = self._runs.get(event.run_id)
        if record is not None:
            record.on_map_created(event)

    @hookimpl
    def slamkit_frame_skipped(self, event: FrameSkipped) -> None:
        record = self._runs.get(event.run_id)
        if record is not None:
            record.on_frame_skipped(event)

    @hookimpl
    def slamkit_frame_tracked(self, event: FrameTracked) -> None:
        record = self._runs.get(event.run_id)
        if record is not None:
            record.on_frame_tracked(event)

    @hookimpl
    def slamkit_keyframe_inserted(self, event: KeyFrameInserted) -> None:
        record = self._runs.get(event.run_id)
        if record is not None:
            record.on_keyframe_inserted(event)

    @hookimpl
    def slamkit_keyframe_culled(self, event: KeyFrameCulled) -> None:
        record = self._runs.get(event.run_id)
        if record is not None:
            record.on_keyframe_culled(event)

    @hookimpl
    def slamkit_loop_checked(self, event: LoopChecked) -> None:
        record = self._runs.get(event.run_id)
        if record is not None:
            record.on_loop_checked(event)

    @hookimpl
    def slamkit_maps_merged(self, event: MapsMerged) -> None:
        record = self._runs.get(event.run_id)
        if record is not None:
            record.on_maps_merged(event)

    @hookimpl
    def slamkit_run_finished(self, event: RunFinished) -> None:
        record = self._runs.pop(event.run_id, None)
        if record is None:
            return
        record.on_run_finished(event)
        assert record.started.run_dir is not None
        write_outputs(record.started.run_dir, record)


#: The instance the entry point names (``slamkit.eval.outputs:plugin``).
plugin = RunOutputs()


def write_outputs(out_dir: Path, record: RunRecord) -> dict[str, Any]:
    """Write what the run has (also after a failure) and return its metrics."""
    from omegaconf import OmegaConf

    from slamkit.eval.run_metrics import map_metrics, run_metrics
    from slamkit.io.trajectory_io import write_trajectory

    started, finished = record.started, record.finished
    if finished is None:
        raise ValueError("write_outputs: the run has not finished (no slamkit_run_finished event)")
    out_dir.mkdir(parents=True, exist_ok=True)
    # the map's trajectory: with the earlier sessions' frames a loaded map file kept (map.load); the metrics and the
    # plot are this run's frames (its ground truth, its frame counts)
    frames = record.frames(loaded=False)
    keyframes = record.keyframes()
    write_trajectory(out_dir / "trajectory.tum", record.frames(), "tum")
    write_trajectory(out_dir / "keyframes.tum", keyframes, "tum")
    (out_dir / "config.yaml").write_text(OmegaConf.to_yaml(OmegaConf.create(dict(started.config))))
    gt = started.ground_truth
    metrics = run_metrics(record, record.main_map, frames, keyframes, started.dataset, gt, record.maps)
    metrics["maps"] = []
    for snap in record.maps:
        map_dir = out_dir / "maps" / str(snap.map_id)
        map_dir.mkdir(parents=True, exist_ok=True)
        map_frames, map_keyframes = record.frames(snap, loaded=False), record.keyframes(snap)
        write_trajectory(map_dir / "trajectory.tum", record.frames(snap), "tum")
        write_trajectory(map_dir / "keyframes.tum", map_keyframes, "tum")
        _write_frames_csv(map_dir / "frames.csv", [o for o in record.tracking if o.map_id == snap.map_id])
        metrics["maps"].append(map_metrics(snap, map_frames, map_keyframes, gt))
    metrics["status"] = finished.status
    metrics["seed"] = int(started.config["seed"]) if "seed" in started.config else None
    if finished.error:
        metrics["error"] = finished.error
    if finished.failed_thread is not None:
        metrics["failed_thread"] = finished.failed_thread
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2, default=float) + "\n")
    write_run_logs(out_dir, record)
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


def write_run_logs(out_dir: Path, record: RunRecord) -> None:
    """frames.csv: what tracking did with each frame; loops.json: what loop closing did with each keyframe
    (candidates, consistency, BoW matches, Sim3 inliers and scale, corrections; merge candidates, their verification
    and a merge's counts and timings), so a user can see why a loop was or was not closed, or two maps merged."""
    dropped = record.finished.dropped_frames if record.finished is not None else ()
    _write_frames_csv(out_dir / "frames.csv", record.tracking, record.skipped, dropped)
    loops = [
        dict(lp.record)
        for lp in record.loops
        if lp.record.get("candidates")
        or lp.record.get("pending")
        or lp.loop_kf_id is not None
        or lp.record.get("merge_candidates")
        or lp.record.get("merge_pending")
    ]
    (out_dir / "loops.json").write_text(json.dumps(loops, indent=2, default=float) + "\n")


def _write_frames_csv(
    path: Path,
    tracking: Sequence[FrameTracked],
    skipped: Sequence[FrameSkipped] = (),
    dropped: Sequence[tuple[int, float]] = (),
) -> None:
    """One row per frame in frame order: what tracking did with it, ``skipped`` (no timestamp: the frame could not
    be read) with the reading error as its message, or ``dropped`` (real-time playback: the frame arrived while
    tracking was busy and a newer one replaced it; dropped: (frame index, timestamp s) each)."""
    rows: list[tuple[int, list[object]]] = [
        (
            o.frame_index,
            [
                o.frame_index,
                f"{o.timestamp_s:.6f}",
                o.state,
                o.method,
                o.n_features,
                o.inliers,
                f"{o.timings_ms.get('track_ms', float('nan')):.2f}",
                o.message,
            ],
        )
        for o in tracking
    ]
    rows += [(s.frame_index, [s.frame_index, "", "skipped", "", 0, 0, "", s.reason]) for s in skipped]
    rows += [
        (i, [i, f"{t:.6f}", "dropped", "", 0, 0, "", "tracking busy: a newer frame replaced it"]) for i, t in dropped
    ]
    rows.sort(key=lambda row: row[0])  # stable: a frame's rows keep their order
    with path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["frame", "timestamp_s", "state", "method", "features", "inliers", "track_ms", "message"])
        writer.writerows(row for _, row in rows)


__all__ = ["PLUGIN_NAME", "RunOutputs", "plugin", "write_outputs", "write_run_logs"]
