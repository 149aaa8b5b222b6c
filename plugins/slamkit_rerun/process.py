"""The viewer in a process of its own: the run's hooks pickle their events into a pipe and return; the child
process draws them with rerun (its JPEG encoding, its arrays, rerun's own encoder and file-writer threads).

Why a process and not a thread: a thread of the run's process shares its GIL and its CPU with tracking, and on a
2-core machine that measured 1.10x on tracking's median (benchmarks/viewer_overhead.py). A child process has a GIL
of its own and runs at a lower priority (``viewer.niceness``), so the kernel gives tracking the core first; what
tracking still pays is pickling each event (a memory copy of the image) in multiprocessing's feeder thread.

The child keeps slamkit_rerun.worker's thread: when it falls behind, a stale frame is drawn without its image.
A child that fails (an exception while drawing, killed, no display) is reported once by the parent — at the next
event or at the end of the run — and the run goes on without it.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import queue
from typing import Any

from slamkit.events import RunFinished, RunStarted
from slamkit.runtime.priority import lower_process_priority
from slamkit_rerun.settings import ViewerSettings

log = logging.getLogger("slamkit_rerun.plugin")

#: Seconds the end of a run waits for the viewer process to draw what is queued and close its recording.
CLOSE_TIMEOUT_S = 120.0

Message = tuple[str, Any, bool]  # (RerunViewer method name, its event, is a per-frame event)


def serve(settings: ViewerSettings, started: RunStarted, inbox: Any, errors: Any) -> None:
    """The child process: draw the messages of ``inbox`` until ``None`` arrives; an error goes to ``errors`` as
    one line of text and ends the process."""
    import importlib

    from slamkit_rerun.viewer import RerunViewer
    from slamkit_rerun.worker import ViewerThread

    try:
        viewer = RerunViewer(importlib.import_module("rerun"), settings, started)
    except Exception as exc:
        errors.put(f"could not open rerun ({type(exc).__name__}: {exc})")
        return

    def failed(exc: BaseException) -> None:
        errors.put(f"{type(exc).__name__}: {exc}")
        with contextlib.suppress(Exception):  # already reported
            viewer.close()

    thread = ViewerThread("viewer", settings.skip_stale_frames, failed)

    def draw(name: str, event: Any) -> Any:
        if name == "frame_tracked":
            return lambda stale: viewer.frame_tracked(event, stale=stale)
        if name == "run_finished":
            return lambda _: viewer.run_finished(event, frames_skipped=thread.frames_skipped)
        return lambda _: getattr(viewer, name)(event)

    while True:
        message: Message | None = inbox.get()
        if message is None or thread.failed:
            break
        name, event, is_frame = message
        thread.submit(draw(name, event), is_frame=is_frame)
    thread.close()
    if thread.frames_skipped and not thread.failed:
        errors.put(f"skipped: {thread.frames_skipped}")  # not an error: the parent logs it as information


class ViewerProcess:
    """The parent's end: starts the child at the run's start, forwards events, reports its failure once."""

    def __init__(self, settings: ViewerSettings, started: RunStarted) -> None:
        context = multiprocessing.get_context("spawn")  # fork is unsafe in a process with threads
        self._inbox = context.Queue()
        # never wait for the queue's feeder thread at exit: after the child died, the feeder can block for good on a
        # full pipe, and the default join would then hang the run's process (a normal end has drained it)
        self._inbox.cancel_join_thread()
        self._errors = context.Queue()
        self._process = context.Process(
            target=serve,
            args=(settings, started, self._inbox, self._errors),
            name=f"slamkit-viewer-{started.run_id}",
            daemon=True,  # never outlives the run's process
        )
        self._process.start()
        assert self._process.pid is not None
        lower_process_priority(self._process.pid, settings.niceness)
        self._failed = False

    def _check_alive(self) -> bool:
        """False (after reporting the failure once) when the child has stopped."""
        if self._failed:
            return False
        if self._process.is_alive():
            return True
        self._failed = True
        self._report(f"the viewer process stopped (exit code {self._process.exitcode})")
        return False

    def _report(self, fallback: str) -> None:
        message = fallback
        with contextlib.suppress(queue.Empty):
            while True:
                line = self._errors.get(timeout=0.5)
                if not line.startswith("skipped: "):
                    message = line
                    break
                log.info("viewer: %s frame images not drawn to keep up with tracking", line.split(": ", 1)[1])
        log.warning("viewer: %s — the run goes on without it", message)

    def send(self, name: str, event: Any, *, is_frame: bool = False) -> None:
        """Queue ``event`` for the child's ``RerunViewer.<name>`` (returns at once)."""
        if self._check_alive():
            self._inbox.put((name, event, is_frame))

    def finish(self, event: RunFinished) -> None:
        """Send the end of the run and wait for the child to close its recording (the .rrd is complete after)."""
        if not self._check_alive():
            return
        self._inbox.put(("run_finished", event, False))
        self._inbox.put(None)
        self._process.join(CLOSE_TIMEOUT_S)
        if self._process.is_alive():
            log.warning("viewer: still drawing after %.0f s at the end of the run; stopped", CLOSE_TIMEOUT_S)
            self._process.terminate()
            return
        report: list[str] = []
        with contextlib.suppress(queue.Empty):
            while True:
                report.append(self._errors.get(timeout=0.2 if not report else 0.05))
        for line in report:
            if line.startswith("skipped: "):
                log.info("viewer: %s frame images not drawn to keep up with tracking", line.split(": ", 1)[1])
            else:
                log.warning("viewer: %s — the run goes on without it", line)
        if self._process.exitcode not in (0, None) and not report:
            log.warning("viewer: the viewer process stopped (exit code %s)", self._process.exitcode)
