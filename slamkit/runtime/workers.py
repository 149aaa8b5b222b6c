"""The pipeline's worker threads (local mapping, loop closing): an inbox, pausing at safe points, abort, faults.

A worker waits on a condition variable (no polling) for an item in its inbox. Between items it is at a *safe
point*: nothing of the map is half-changed by it. ``pause()`` returns a Future that resolves once the worker is
parked at a safe point; the worker stays parked until ``resume()`` (loop correction uses this to stop local
mapping, DESIGN section 4). The abort token is set by ``pause()``, ``stop()`` and by the runner when tracking
needs a keyframe inserted (ORB-SLAM V-E: "a signal is sent to stop local BA"); the worker's process function
sees it and cuts its optimization short. An exception in the process function ends the worker: it records the
thread's name and traceback and calls the runner's fault handler, so the run stops instead of hanging.
"""

from __future__ import annotations

import threading
import traceback
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Generic, TypeVar

from slamkit.errors import SlamkitError
from slamkit.runtime.priority import lower_thread_priority

Item = TypeVar("Item")


class PipelineThreadError(SlamkitError):
    """A pipeline thread raised: the run stopped. Carries the thread's name and its formatted traceback."""

    def __init__(self, thread_name: str, exc: BaseException, formatted_traceback: str) -> None:
        super().__init__(f"the {thread_name} thread failed: {type(exc).__name__}: {exc}\n{formatted_traceback}")
        self.thread_name = thread_name
        self.exc = exc
        self.formatted_traceback = formatted_traceback


def raised_by_ctrl_c(exc: BaseException) -> bool:
    """Whether Ctrl-C caused ``exc``. Python runs the SIGINT handler at the next bytecode of the main thread; when
    that bytecode is a callback from compiled code (numba unpickling a constant at the end of a nogil kernel, say),
    the KeyboardInterrupt reaches the caller wrapped in a SystemError, with the interrupt as its cause."""
    seen: set[int] = set()
    cause: BaseException | None = exc
    while cause is not None and id(cause) not in seen:
        if isinstance(cause, KeyboardInterrupt):
            return True
        seen.add(id(cause))
        cause = cause.__cause__ or cause.__context__
    return False


@dataclass(frozen=True)
class ThreadFault:
    """An exception that ended a pipeline thread."""

    thread_name: str
    exc: BaseException
    formatted_traceback: str

    def as_error(self) -> PipelineThreadError:
        return PipelineThreadError(self.thread_name, self.exc, self.formatted_traceback)


class PipelineWorker(threading.Thread, Generic[Item]):
    """One pipeline thread processing items in arrival order.

    process: called with each item and the worker's abort token (a threading.Event, cleared before each item).
    on_fault: called once, from this thread, when ``process`` raises; the worker then exits.
    niceness: how much the thread lowers its own scheduling priority when it starts (0: not at all; see
        slamkit/runtime/priority.py): background work yields the cores to tracking.
    """

    def __init__(
        self,
        name: str,
        process: Callable[[Item, threading.Event], None],
        on_fault: Callable[[ThreadFault], None],
        niceness: int = 0,
    ) -> None:
        super().__init__(name=name, daemon=True)
        self.niceness = niceness
        self.priority_lowered = False
        self._process = process
        self._on_fault = on_fault
        self._cond = threading.Condition()
        self._inbox: deque[Item] = deque()
        self._busy = False
        self._stop_requested = False
        self._drain_then_stop = False
        self._pause_requests: list[tuple[Future[None], bool]] = []  # (future, finish_queue)
        self._paused = False
        self.abort = threading.Event()
        self.fault: ThreadFault | None = None
        self.processed = 0

    # ---- called from other threads -------------------------------------------------------------

    def submit(self, item: Item) -> None:
        """Queue an item (never blocks)."""
        with self._cond:
            self._inbox.append(item)
            self._cond.notify_all()

    def idle(self) -> bool:
        """True when nothing is queued and no item is being processed (ORB-SLAM's AcceptKeyFrames)."""
        with self._cond:
            return not self._busy and not self._inbox

    def pending(self) -> int:
        """Items queued and not yet started."""
        with self._cond:
            return len(self._inbox)

    def pause(self, finish_queue: bool = False) -> Future[None]:
        """Ask the worker to park at a safe point; the Future resolves when it is parked (or fails with the
        worker's error if it died).

        finish_queue=False: park after the current item, whose optimization is asked to stop early (map reset).
        finish_queue=True: park once the inbox is empty (ORB-SLAM's local mapping only stops for loop closing
        with no keyframe waiting, so every keyframe is in the map the correction moves).
        """
        fut: Future[None] = Future()
        with self._cond:
            if self.fault is not None:
                fut.set_exception(self.fault.as_error())
                return fut
            at_safe_point = not self._busy and (not finish_queue or not self._inbox)
            if not self.is_alive() or self._paused or at_safe_point:
                self._paused = True
                fut.set_result(None)
                return fut
            self._pause_requests.append((fut, finish_queue))
            if not finish_queue:
                self.abort.set()
            self._cond.notify_all()
        return fut

    def stopping(self) -> bool:
        """True while the worker is parked or asked to park (tracking then inserts no keyframe, ORB-SLAM V-E)."""
        with self._cond:
            return self._paused or bool(self._pause_requests)

    def resume(self) -> None:
        """Let a paused worker go on."""
        with self._cond:
            self._paused = False
            self._cond.notify_all()

    def clear(self) -> int:
        """Drop every queued item (the map was reset); returns how many were dropped."""
        with self._cond:
            n = len(self._inbox)
            self._inbox.clear()
            return n

    def stop(self, drain: bool) -> None:
        """Ask the worker to exit: after processing what is queued (drain) or at once (the current item's
        optimization is aborted)."""
        with self._cond:
            if drain:
                self._drain_then_stop = True
            else:
                self._stop_requested = True
                self.abort.set()
            self._paused = False
            self._cond.notify_all()

    # ---- the thread ------------------------------------------------------------------------------

    def _next_item(self) -> tuple[bool, Item | None]:
        """Wait for an item; (False, None) when the worker should exit."""
        with self._cond:
            self._busy = False
            waiting: list[tuple[Future[None], bool]] = []
            for fut, finish_queue in self._pause_requests:
                if finish_queue and self._inbox:
                    waiting.append((fut, finish_queue))
                else:
                    fut.set_result(None)
                    self._paused = True
            self._pause_requests = waiting
            self._cond.notify_all()
            while not self._stop_requested:
                if self._inbox and not self._paused:
                    self._busy = True
                    self.abort.clear()
                    return True, self._inbox.popleft()
                if self._drain_then_stop and not self._inbox:
                    return False, None
                self._cond.wait()
            return False, None

    def run(self) -> None:
        try:
            self.priority_lowered = lower_thread_priority(self.niceness)
            while True:
                go, item = self._next_item()
                if not go:
                    return
                self._process(item, self.abort)  # type: ignore[arg-type]
                self.processed += 1
        except BaseException as exc:  # a thread must report every failure, KeyboardInterrupt included
            fault = ThreadFault(self.name, exc, traceback.format_exc())
            with self._cond:
                self.fault = fault
                self._busy = False
                for fut, _ in self._pause_requests:
                    fut.set_exception(fault.as_error())
                self._pause_requests.clear()
                self._cond.notify_all()
            self._on_fault(fault)

    def wait_idle(self, timeout_s: float | None = None) -> bool:
        """Block until the inbox is empty and no item is in progress (or the worker died)."""
        with self._cond:
            return self._cond.wait_for(
                lambda: self.fault is not None or (not self._busy and not self._inbox) or not self.is_alive(),
                timeout=timeout_s,
            )
