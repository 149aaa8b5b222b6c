"""The viewer's own thread: the pipeline's hooks hand their events over and return at once; the thread logs them to
rerun in order. A viewer that does its drawing (JPEG encoding, building rerun's arrays) in the pipeline's threads
slows tracking by what it draws; here tracking pays only for a queue append and for sharing the GIL.

When the thread falls behind (a frame event is waiting while newer frames have arrived), a stale frame's image and
features are not drawn — the pose, the trajectory and the plots still are — as a live view shows the latest image,
not a backlog. Keyframes, map points, loops, merges and the end of the run are never skipped.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

log = logging.getLogger(__name__)


@dataclass
class Job:
    """One event to log: ``draw(stale)`` logs it; ``stale`` is True for a frame event with newer frames queued
    behind it (when stale images are skipped). is_frame: a per-frame event (the only kind that can be stale)."""

    draw: Callable[[bool], None]
    is_frame: bool


class ViewerThread:
    """A daemon thread that runs submitted jobs in order.

    skip_stale_frames: draw a frame event's image/features only when no newer frame event is queued (live view);
    False draws every frame (a complete recording, at tracking's expense when the thread cannot keep up).
    on_error(exc): called once, in the thread, by the first job that raises; the jobs after it are dropped."""

    def __init__(self, name: str, skip_stale_frames: bool, on_error: Callable[[BaseException], None]) -> None:
        self._skip_stale = skip_stale_frames
        self._on_error = on_error
        self._jobs: deque[Job] = deque()
        self._frames_queued = 0  # frame jobs in self._jobs
        self._cond = threading.Condition()
        self._closing = False
        self._failed = False
        self.frames_skipped = 0  # frame events drawn without their image (stale)
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    @property
    def failed(self) -> bool:
        return self._failed

    def submit(self, draw: Callable[[bool], None], *, is_frame: bool = False) -> None:
        """Queue ``draw`` (called later, in the viewer thread, with ``stale``); ignored once the viewer failed."""
        with self._cond:
            if self._failed or self._closing:
                return
            self._jobs.append(Job(draw, is_frame))
            self._frames_queued += is_frame
            self._cond.notify()

    def close(self, timeout_s: float | None = None) -> bool:
        """Let the thread draw what is queued, then stop it; True if it finished within ``timeout_s``."""
        with self._cond:
            self._closing = True
            self._cond.notify()
        self._thread.join(timeout_s)
        return not self._thread.is_alive()

    def _loop(self) -> None:
        while True:
            with self._cond:
                while not self._jobs and not self._closing:
                    self._cond.wait()
                if not self._jobs:
                    return  # closing and drained
                job = self._jobs.popleft()
                self._frames_queued -= job.is_frame
                stale = self._skip_stale and job.is_frame and self._frames_queued > 0
            self.frames_skipped += stale
            try:
                job.draw(stale)
            except Exception as exc:  # the viewer never stops the run: report once, drop the rest
                with self._cond:
                    self._failed = True
                    self._jobs.clear()
                    self._frames_queued = 0
                self._on_error(exc)
                return
