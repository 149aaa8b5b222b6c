"""Entry point of the slamkit_rerun plugin: one :class:`RerunViewer` per run whose config selects it
(``+viewer=rerun``). A failure of the viewer (rerun missing, no display to spawn on, a file that cannot be written,
an error while logging) is logged once and ends the viewing; the run goes on. The viewer draws in a process of its
own (slamkit_rerun.process; ``viewer.process=false``: a thread, slamkit_rerun.worker): the pipeline's hooks only
queue their events."""

from __future__ import annotations

import contextlib
import importlib
import logging
from typing import Any

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
from slamkit_rerun.process import ViewerProcess
from slamkit_rerun.settings import ViewerSettings
from slamkit_rerun.viewer import RerunViewer
from slamkit_rerun.worker import ViewerThread

log = logging.getLogger(__name__)


class ViewerInThread:
    """The viewer in a thread of the run's process (``viewer.process=false``): same interface as ViewerProcess."""

    def __init__(self, viewer: RerunViewer, settings: ViewerSettings, run_id: int) -> None:
        self.viewer = viewer

        def failed(exc: BaseException) -> None:  # the viewer never stops the run: say it once, stop viewing
            log.warning("viewer: %s: %s — the run goes on without it", type(exc).__name__, exc)
            with contextlib.suppress(Exception):  # already reported above
                viewer.close()

        self.thread = ViewerThread(f"viewer-{run_id}", settings.skip_stale_frames, failed)

    def send(self, name: str, event: Any, *, is_frame: bool = False) -> None:
        viewer = self.viewer
        if is_frame:
            self.thread.submit(lambda stale: viewer.frame_tracked(event, stale=stale), is_frame=True)
        else:
            self.thread.submit(lambda _: getattr(viewer, name)(event))

    def finish(self, event: RunFinished) -> None:
        thread = self.thread
        thread.submit(lambda _: self.viewer.run_finished(event, frames_skipped=thread.frames_skipped))
        thread.close()
        if thread.frames_skipped and not thread.failed:
            log.info("viewer: %d frame images not drawn to keep up with tracking", thread.frames_skipped)


class RerunViewerPlugin:
    """The lifecycle-hook listener: hands each run's events to its viewer (a process of its own by default,
    slamkit_rerun.process), so the pipeline's threads never wait for drawing."""

    def __init__(self) -> None:
        self._viewers: dict[int, ViewerProcess | ViewerInThread] = {}

    def _send(self, run_id: int, name: str, event: Any, *, is_frame: bool = False) -> None:
        viewer = self._viewers.get(run_id)
        if viewer is not None:
            viewer.send(name, event, is_frame=is_frame)

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
            if settings.process:
                self._viewers[event.run_id] = ViewerProcess(settings, event)
            else:
                self._viewers[event.run_id] = ViewerInThread(RerunViewer(rr, settings, event), settings, event.run_id)
        except Exception as exc:
            log.warning("viewer: could not open rerun (%s: %s); the run goes on without it", type(exc).__name__, exc)
            return
        where = settings.save or settings.connect or "a new rerun viewer"
        log.info("viewer: streaming the run to %s", where)

    @hookimpl
    def slamkit_frame_tracked(self, event: FrameTracked) -> None:
        self._send(event.run_id, "frame_tracked", event, is_frame=True)

    @hookimpl
    def slamkit_map_created(self, event: MapCreated) -> None:
        self._send(event.run_id, "map_created", event)

    @hookimpl
    def slamkit_keyframe_inserted(self, event: KeyFrameInserted) -> None:
        self._send(event.run_id, "keyframe_inserted", event)

    @hookimpl
    def slamkit_keyframe_culled(self, event: KeyFrameCulled) -> None:
        self._send(event.run_id, "keyframe_culled", event)

    @hookimpl
    def slamkit_loop_closed(self, event: LoopClosed) -> None:
        self._send(event.run_id, "loop_closed", event)

    @hookimpl
    def slamkit_maps_merged(self, event: MapsMerged) -> None:
        self._send(event.run_id, "maps_merged", event)

    @hookimpl
    def slamkit_run_finished(self, event: RunFinished) -> None:
        """The final maps are drawn and the recording closed before the run returns (the .rrd is complete)."""
        viewer = self._viewers.pop(event.run_id, None)
        if viewer is not None:
            viewer.finish(event)


plugin: Any = RerunViewerPlugin()
