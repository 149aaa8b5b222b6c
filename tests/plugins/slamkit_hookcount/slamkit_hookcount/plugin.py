"""Counts what a run does through slamkit's lifecycle hooks, as a third-party logger would, and writes the counts
to ``hook_counts.json`` in the run directory when the run finishes (nothing when the run has no directory).

Only the public API is used: ``slamkit.hookspecs.hookimpl`` and the event dataclasses of ``slamkit.events``.
"""

from __future__ import annotations

import json
import threading
from collections import Counter
from pathlib import Path

from slamkit.events import (
    FrameTracked,
    KeyFrameCulled,
    KeyFrameInserted,
    LoopChecked,
    LoopClosed,
    MapCreated,
    PointsCulled,
    RunFinished,
    RunStarted,
)
from slamkit.hookspecs import hookimpl


class HookCounter:
    """Per run (keyed on ``run_id``): how many times each hook fired, and on which threads."""

    def __init__(self) -> None:
        self._runs: dict[int, tuple[Path | None, Counter[str], set[str]]] = {}

    def _count(self, run_id: int, what: str, n: int = 1) -> None:
        run = self._runs.get(run_id)
        if run is not None:
            run[1][what] += n
            run[2].add(threading.current_thread().name)

    @hookimpl
    def slamkit_run_started(self, event: RunStarted) -> None:
        self._runs[event.run_id] = (event.run_dir, Counter(), {threading.current_thread().name})

    @hookimpl
    def slamkit_frame_tracked(self, event: FrameTracked) -> None:
        self._count(event.run_id, "frames_tracked")
        if event.state == "ok":
            self._count(event.run_id, "frames_ok")

    @hookimpl
    def slamkit_map_created(self, event: MapCreated) -> None:
        self._count(event.run_id, "maps_created")

    @hookimpl
    def slamkit_keyframe_inserted(self, event: KeyFrameInserted) -> None:
        self._count(event.run_id, "keyframes_inserted")

    @hookimpl
    def slamkit_keyframe_culled(self, event: KeyFrameCulled) -> None:
        self._count(event.run_id, "keyframes_culled")

    @hookimpl
    def slamkit_points_culled(self, event: PointsCulled) -> None:
        self._count(event.run_id, "points_culled", event.n_points)

    @hookimpl
    def slamkit_loop_checked(self, event: LoopChecked) -> None:
        self._count(event.run_id, "loops_checked")

    @hookimpl
    def slamkit_loop_closed(self, event: LoopClosed) -> None:
        self._count(event.run_id, "loops_closed")

    @hookimpl
    def slamkit_run_finished(self, event: RunFinished) -> None:
        run_dir, counts, threads = self._runs.pop(event.run_id)
        if run_dir is None:
            return
        threads.add(threading.current_thread().name)
        record = {
            **counts,
            "status": event.status,
            "resets": event.resets,
            "keyframes_at_end": sum(m.n_keyframes for m in event.maps),
            "threads": sorted(threads),
        }
        Path(run_dir, "hook_counts.json").write_text(json.dumps(record, indent=2) + "\n")


plugin = HookCounter()
