"""Entry point of the slamkit_rerun plugin: one :class:`RerunViewer` per run whose config selects it
(``+viewer=rerun``). A failure of the viewer (rerun missing, no display to spawn on, a file that cannot be written,
an error while logging) is logged once and ends the viewing; the run goes on."""

from __future__ import annotations

import contextlib
import importlib
import logging
from collections.abc import Callable
from typing import Any, TypeVar

from slamkit.events import (
    FrameTracked,
    KeyFrameCulled,
    KeyFrameInserted,
    LoopClosed,
    MapCreated,
    MapsMerged,
    RunFinished,
    RunStarted,
)
from slamkit.hookspecs import hookimpl
from slamkit_rerun.settings import ViewerSettings
from slamkit_rerun.viewer import RerunViewer

log = logging.getLogger(__name__)

E = TypeVar("E")


class RerunViewerPlugin:
    """The lifecycle-hook listener: dispatches each run's events to its viewer."""

    def __init__(self) -> None:
        self._viewers: dict[int, RerunViewer] = {}

    def _call(self, run_id: int, method: Callable[[RerunViewer], None]) -> None:
        viewer = self._viewers.get(run_id)
        if viewer is None:
            return
        try:
            method(viewer)
        except Exception as exc:  # the viewer never stops the run: say it once, stop viewing
            log.warning("viewer: %s: %s — the run goes on without it", type(exc).__name__, exc)
            self._viewers.pop(run_id, None)
            with contextlib.suppress(Exception):  # already reported above
                viewer.close()

    @hookimpl
    def slamkit_run_started(self, event: RunStarted) -> None:
        settings = ViewerSettings.from_config(event.config)
        if settings is None:
            return
        try:
            rr = importlib.import_module("rerun")
        except ImportError:
            log.warning("viewer: rerun is not installed (pip install 'slamkit[viewer]'); the run goes on without it")
            return
        try:
            self._viewers[event.run_id] = RerunViewer(rr, settings, event)
        except Exception as exc:
            log.warning("viewer: could not open rerun (%s: %s); the run goes on without it", type(exc).__name__, exc)
            return
        where = settings.save or settings.connect or "a new rerun viewer"
        log.info("viewer: streaming the run to %s", where)

    @hookimpl
    def slamkit_frame_tracked(self, event: FrameTracked) -> None:
        self._call(event.run_id, lambda v: v.frame_tracked(event))

    @hookimpl
    def slamkit_map_created(self, event: MapCreated) -> None:
        self._call(event.run_id, lambda v: v.map_created(event))

    @hookimpl
    def slamkit_keyframe_inserted(self, event: KeyFrameInserted) -> None:
        self._call(event.run_id, lambda v: v.keyframe_inserted(event))

    @hookimpl
    def slamkit_keyframe_culled(self, event: KeyFrameCulled) -> None:
        self._call(event.run_id, lambda v: v.keyframe_culled(event))

    @hookimpl
    def slamkit_loop_closed(self, event: LoopClosed) -> None:
        self._call(event.run_id, lambda v: v.loop_closed(event))

    @hookimpl
    def slamkit_maps_merged(self, event: MapsMerged) -> None:
        self._call(event.run_id, lambda v: v.maps_merged(event))

    @hookimpl
    def slamkit_run_finished(self, event: RunFinished) -> None:
        self._call(event.run_id, lambda v: v.run_finished(event))
        self._viewers.pop(event.run_id, None)


plugin: Any = RerunViewerPlugin()
