"""Firing the lifecycle hooks (slamkit/hookspecs.py) from the runners: the dispatcher and the events of one run.

:class:`EventDispatcher` calls the plugins' implementations of the ``slamkit_*`` lifecycle hooks, each on its
own, so that a listener's exception is logged with its plugin's name and stops only that listener (for the rest
of the run), never the run; a *critical* plugin (the run's own outputs, ``slamkit.eval.outputs``) is the
exception: its failure is raised when the run ends.

Threads. The sequential runner calls the listeners inline, from its one thread, in a fixed order (deterministic,
like everything it does). The threaded runner starts the dispatcher's own thread: tracking, local mapping and
loop closing only put ``(hook, event)`` on a queue (a few microseconds: building a small frozen dataclass and a
lock-free ``SimpleQueue.put``), and the dispatcher thread calls the listeners one event at a time in the order
the events were queued. So a listener's cost never lands on tracking (a viewer that draws for 20 ms per frame
delays only the dispatcher thread; it still shares the GIL, so a listener should do its heavy work in numpy,
OpenCV or its own process), events reach every listener in one total order consistent with each thread's own
order, and a listener never needs a lock. Calling listeners from the thread that produced the event was the
alternative; it was rejected because a slow or blocking listener would then stall tracking directly.

:class:`RunEvents` is one run's side: it numbers the run and its maps, turns the pipeline's outcomes into the
plain-data events of :mod:`slamkit.events`, and fires them. The algorithms (slamkit/pipeline) never see it.
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
import traceback
import uuid
from collections.abc import Collection, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from slamkit.errors import PluginError
from slamkit.events import (
    FrameSkipped,
    FrameTracked,
    InitialKeyFrame,
    KeyFrameCulled,
    KeyFrameInserted,
    LoopChecked,
    LoopClosed,
    MapCreated,
    MapsMerged,
    MapSnapshot,
    PointsCulled,
    RunFinished,
    RunStarted,
)
from slamkit.geometry.se3 import invert_T
from slamkit.interfaces import Dataset
from slamkit.map.atlas import Atlas
from slamkit.pipeline.frame import Frame
from slamkit.pipeline.outcomes import LoopOutcome, MappingOutcome, TrackingOutcome
from slamkit.runtime.log import RunLog
from slamkit.runtime.source import frame_count

log = logging.getLogger("slamkit.events")

#: The lifecycle hooks, in the order a run fires them first.
LIFECYCLE_HOOKS = (
    "slamkit_run_started",
    "slamkit_map_created",
    "slamkit_frame_skipped",
    "slamkit_frame_tracked",
    "slamkit_keyframe_inserted",
    "slamkit_points_culled",
    "slamkit_keyframe_culled",
    "slamkit_loop_checked",
    "slamkit_loop_closed",
    "slamkit_maps_merged",
    "slamkit_run_finished",
)

_STOP = object()


@dataclasses.dataclass(frozen=True)
class _Listener:
    plugin: str
    function: Any
    argnames: tuple[str, ...]


class EventDispatcher:
    """Calls the plugins' lifecycle hook implementations.

    hooks: the plugin manager's hook relay (``ComponentRegistry.hook``; None: nobody listens); the listeners are
    the implementations registered when the dispatcher is built, called in registration order. critical: names
    of plugins whose failure fails the run (the run's own outputs); any other listener that raises is logged with
    its plugin's name and not called again during the run.

    Use: ``start(threaded)`` at the beginning of a run, ``emit`` from any thread, ``close()`` at its end (drains
    the queue, joins the dispatcher thread, raises a critical plugin's failure).
    """

    def __init__(self, hooks: Any | None = None, critical: Collection[str] = ()) -> None:
        self.critical = frozenset(critical)
        self._listeners: dict[str, list[_Listener]] = {name: [] for name in LIFECYCLE_HOOKS}
        if hooks is not None:
            for name in LIFECYCLE_HOOKS:
                caller = getattr(hooks, name, None)
                if caller is None:
                    continue
                for impl in caller.get_hookimpls():
                    if impl.hookwrapper or impl.wrapper:
                        log.warning("plugin '%s': %s as a wrapper is not supported; ignored", impl.plugin_name, name)
                        continue
                    self._listeners[name].append(_Listener(impl.plugin_name, impl.function, tuple(impl.argnames)))
        self._disabled: set[str] = set()
        self._critical_error: tuple[str, str, BaseException] | None = None
        self._queue: queue.SimpleQueue[Any] | None = None
        self._thread: threading.Thread | None = None

    def wants(self, hook: str) -> bool:
        """Whether any plugin listens to ``hook`` (skip building an event nobody reads)."""
        return bool(self._listeners[hook])

    def start(self, threaded: bool) -> None:
        """Begin a run: threaded = deliver events from the dispatcher's own thread (see the module docstring)."""
        self._disabled.clear()
        self._critical_error = None
        if threaded and any(self._listeners.values()):
            self._queue = queue.SimpleQueue()
            self._thread = threading.Thread(target=self._deliver_queued, name="lifecycle-events", daemon=True)
            self._thread.start()

    def emit(self, hook: str, event: object) -> None:
        """Fire ``hook`` with ``event`` (queued for the dispatcher thread when one runs)."""
        if not self._listeners[hook]:
            return
        if self._queue is not None:
            self._queue.put((hook, event))
        else:
            self._deliver(hook, event)

    def close(self, raise_critical: bool = True) -> None:
        """End of the run: deliver what is queued, stop the dispatcher thread, and raise a critical plugin's
        failure as a PluginError (or only log it when ``raise_critical`` is false: the run failed already)."""
        if self._queue is not None and self._thread is not None:
            self._queue.put(_STOP)
            self._thread.join()
        self._queue, self._thread = None, None
        if self._critical_error is not None:
            plugin, hook, exc = self._critical_error
            self._critical_error = None
            message = f"plugin '{plugin}' (the run's outputs) failed in {hook}: {type(exc).__name__}: {exc}"
            if raise_critical:
                raise PluginError(message) from exc
            log.error("%s", message)

    def _deliver_queued(self) -> None:
        inbox = self._queue
        assert inbox is not None
        while True:
            item = inbox.get()
            if item is _STOP:
                return
            self._deliver(*item)

    def _deliver(self, hook: str, event: object) -> None:
        for listener in self._listeners[hook]:
            if listener.plugin in self._disabled:
                continue
            try:
                listener.function(*[event for _ in listener.argnames])
            except Exception as exc:
                self._disabled.add(listener.plugin)
                if listener.plugin in self.critical:
                    if self._critical_error is None:
                        self._critical_error = (listener.plugin, hook, exc)
                    log.error("plugin '%s' failed in %s:\n%s", listener.plugin, hook, traceback.format_exc())
                else:
                    log.error(
                        "plugin '%s' failed in %s (the run goes on; it gets no more events):\n%s",
                        listener.plugin,
                        hook,
                        traceback.format_exc(),
                    )


def describe_exception(exc: BaseException) -> str:
    """The one-line account of the exception that ended a run (``traceback.format_exception_only``)."""
    return "".join(traceback.format_exception_only(type(exc), exc)).strip() or type(exc).__name__


class RunEvents:
    """One run's lifecycle events: numbers the run and its maps and turns the pipeline's outcomes into events.

    A runner makes one at the start of ``run`` and calls it where things happen; tracking's calls come from the
    tracking thread, ``keyframe_mapped`` from local mapping's, ``loop_checked`` from loop closing's.
    """

    def __init__(self, dispatcher: EventDispatcher | None, runner: str, atlas: Atlas) -> None:
        self.dispatcher = dispatcher or EventDispatcher()
        self.runner = runner
        self.atlas = atlas
        self.run_id = uuid.uuid4().int >> 65  # unique within the process (and beyond), fits an int64

    @property
    def map_id(self) -> int:
        """The active map's id in the Atlas (events of local mapping and loop closing are about the active map: the
        runner parks them while the active map changes)."""
        return self.atlas.active_id

    def started(self, dataset: Dataset, run_dir: Path | None, config: Mapping[str, Any] | None, threaded: bool) -> None:
        camera = getattr(dataset, "camera", None)
        K = getattr(camera, "K", None)
        event = RunStarted(
            run_id=self.run_id,
            runner=self.runner,
            dataset=str(getattr(dataset, "name", "?")),
            n_frames=frame_count(dataset),
            run_dir=run_dir,
            config=dict(config or {}),
            ground_truth=getattr(dataset, "ground_truth", None),
            K=None if K is None else np.array(K, dtype=np.float64),
            image_size=None if K is None else (int(camera.width), int(camera.height)),  # type: ignore[union-attr]
            loaded_frames=dict(getattr(self.atlas, "loaded_frames", None) or {}),
        )
        self.dispatcher.start(threaded)
        self.dispatcher.emit("slamkit_run_started", event)

    def frame_skipped(self, frame_index: int, reason: str) -> None:
        """A frame the dataset could not read was left out (slamkit.runtime.source.readable_frames)."""
        if self.dispatcher.wants("slamkit_frame_skipped"):
            self.dispatcher.emit("slamkit_frame_skipped", FrameSkipped(self.run_id, frame_index, reason))

    def map_events(self, out: TrackingOutcome) -> None:
        """Right after tracking a frame: fire map_created when the frame initialised the active map (before local
        mapping sees its keyframes)."""
        if out.initialized_map and out.new_keyframes and self.dispatcher.wants("slamkit_map_created"):
            self.dispatcher.emit(
                "slamkit_map_created",
                MapCreated(
                    run_id=self.run_id,
                    map_id=self.map_id,
                    frame_index=out.frame_index,
                    timestamp_s=out.timestamp_s,
                    keyframes=tuple(
                        InitialKeyFrame(kf.id, kf.frame_index, kf.timestamp_s, kf.T_c_w.copy())
                        for kf in out.new_keyframes
                    ),
                    n_points=len(self.atlas.active.point_ids()),
                ),
            )

    def frame_tracked(
        self,
        out: TrackingOutcome,
        map_reset: bool,
        reference_kf_id: int | None,
        T_ref_w: np.ndarray | None,
        image: np.ndarray | None = None,
        frame: Frame | None = None,
    ) -> None:
        """Fire frame_tracked. reference_kf_id / T_ref_w: the keyframe the frame's pose is recorded against and
        its pose (4, 4) T_c_w at the moment the runner records it (None: no pose to record). image / frame: the
        frame's image and the tracker's Frame of it (keypoints and their map points), passed on for a viewer."""
        if not self.dispatcher.wants("slamkit_frame_tracked"):
            return
        posed = out.T_c_w is not None and T_ref_w is not None and reference_kf_id is not None
        seen = frame is not None and frame.index == out.frame_index
        self.dispatcher.emit(
            "slamkit_frame_tracked",
            FrameTracked(
                run_id=self.run_id,
                map_id=self.map_id,
                frame_index=out.frame_index,
                timestamp_s=out.timestamp_s,
                state=out.state.value,
                method=out.method,
                n_features=out.n_features,
                inliers=out.inliers,
                T_c_w=None if out.T_c_w is None else out.T_c_w.copy(),
                reference_kf_id=reference_kf_id if posed else None,
                # as TrajectoryRecorder.record computes it (same operations: same bits)
                T_c_r=out.T_c_w @ invert_T(T_ref_w) if posed else None,  # type: ignore[operator,arg-type]
                map_reset=map_reset,
                timings_ms=dict(out.timings_ms),
                message=out.message,
                image=image,
                uv_px=frame.features.uv_px if seen else None,  # type: ignore[union-attr]
                tracked=(frame.point_ids >= 0) if seen else None,  # type: ignore[union-attr]
            ),
        )

    def keyframe_mapped(self, outcome: MappingOutcome) -> None:
        """After local mapping processed a keyframe: inserted (with its pose and points as local mapping left them),
        then what its culling removed."""
        emit = self.dispatcher.emit
        store = self.atlas.active
        T_c_w = point_ids = points_w = None
        with store.read():
            if store.has_keyframe(outcome.kf_id):
                kf = store.get_keyframe(outcome.kf_id)
                T_c_w = kf.T_c_w.copy()
                ids = kf.point_ids[kf.point_ids >= 0]
                point_ids = ids[store.has_points(ids)] if ids.size else ids
                points_w = (
                    store.point_rows(point_ids, "xyz_w").astype(np.float64) if point_ids.size else np.zeros((0, 3))
                )
        emit(
            "slamkit_keyframe_inserted",
            KeyFrameInserted(
                run_id=self.run_id,
                map_id=self.map_id,
                kf_id=outcome.kf_id,
                points_created=outcome.points_created,
                points_fused=outcome.points_fused,
                ba_outliers=outcome.ba_outliers,
                ba_aborted=outcome.ba_aborted,
                timings_ms=dict(outcome.timings_ms),
                T_c_w=T_c_w,
                point_ids=point_ids,
                points_w=points_w,
                ba_due=outcome.ba_due,
                ba_skipped=outcome.ba_skipped,
            ),
        )
        if outcome.points_culled:
            emit("slamkit_points_culled", PointsCulled(self.run_id, self.map_id, outcome.kf_id, outcome.points_culled))
        for culled in outcome.culled_keyframes:
            emit(
                "slamkit_keyframe_culled",
                KeyFrameCulled(
                    self.run_id, self.map_id, culled.kf_id, culled.parent_id, culled.T_kf_parent, culled.T_c_w
                ),
            )

    def loop_checked(self, outcome: LoopOutcome) -> None:
        """After loop closing processed a keyframe: what it found, then the loop it closed (if any)."""
        if self.dispatcher.wants("slamkit_loop_checked"):
            self.dispatcher.emit(
                "slamkit_loop_checked",
                LoopChecked(
                    run_id=self.run_id,
                    map_id=self.map_id,
                    kf_id=outcome.kf_id,
                    loop_kf_id=outcome.loop_kf_id,
                    essential_graph_edges=outcome.essential_graph_edges,
                    timings_ms=dict(outcome.timings_ms),
                    record=dataclasses.asdict(outcome),
                ),
            )
        if outcome.loop_kf_id is not None:
            self.dispatcher.emit(
                "slamkit_loop_closed",
                LoopClosed(
                    run_id=self.run_id,
                    map_id=self.map_id,
                    kf_id=outcome.kf_id,
                    loop_kf_id=outcome.loop_kf_id,
                    matches=outcome.matches,
                    scale=float(outcome.scale),
                    essential_graph_edges=outcome.essential_graph_edges,
                    timings_ms=dict(outcome.timings_ms),
                ),
            )

    def maps_merged(
        self, kf_id: int, matched_kf_id: int, merged_map_id: int, into_map_id: int, T_new_old: np.ndarray
    ) -> None:
        """Loop closing merged the map ``merged_map_id`` into the active map (fired as the active map moves)."""
        if self.dispatcher.wants("slamkit_maps_merged"):
            self.dispatcher.emit(
                "slamkit_maps_merged",
                MapsMerged(self.run_id, merged_map_id, into_map_id, kf_id, matched_kf_id, T_new_old.copy()),
            )

    def finished(self, run: RunLog, exc: BaseException | None) -> None:
        """The run ended (``exc``: what ended it, None when it completed): fire run_finished, deliver every
        queued event, and raise a critical plugin's failure (only logged when the run failed already)."""
        try:
            if self.dispatcher.wants("slamkit_run_finished"):
                status = "ok" if exc is None else "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed"
                self.dispatcher.emit(
                    "slamkit_run_finished",
                    RunFinished(
                        run_id=self.run_id,
                        status=status,
                        error=None if exc is None else describe_exception(exc),
                        failed_thread=run.failed_thread,
                        maps=tuple(MapSnapshot.of_store(store, map_id) for map_id, store in self.atlas.items()),
                        resets=run.resets,
                        wall_s=run.wall_s,
                        sequence_s=run.sequence_s,
                        frames_dropped=run.frames_dropped,
                        realtime_factor=run.realtime_factor,
                        preloaded_mb=run.preloaded_mb,
                        dropped_frames=tuple(run.dropped_frames),
                        source_end=run.source_end,
                    ),
                )
        finally:
            self.dispatcher.close(raise_critical=exc is None)
