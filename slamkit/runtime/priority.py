"""Scheduling for the threaded runner: tracking first, background work (local mapping, loop closing) after.

On a machine with few cores the three pipeline threads compete for CPU and, being Python threads, for the GIL.
Tracking is the latency-critical one (a frame it has not finished when the next arrives is a dropped frame), local
mapping and loop closing are throughput work that can take whatever time tracking leaves (ORB-SLAM's own design:
local mapping is given "the time between keyframes"). Two levers, both measured in docs/BENCHMARKS.md:

- Thread niceness (Linux): a background thread raises its own nice value, so when tracking is runnable the kernel
  gives it the core first. Linux keeps a nice value per thread (``setpriority(PRIO_PROCESS, tid, ...)`` acts on one
  thread), raising it needs no privilege, and threads a thread creates inherit it.
- The GIL switch interval: a thread that releases the GIL (an OpenCV or numba call) and wants it back while another
  thread runs Python code waits up to ``sys.getswitchinterval()`` (5 ms by default) before it forces a hand-over.
  Tracking makes dozens of such calls per frame; a shorter interval cuts that wait.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import threading
from collections.abc import Iterator

log = logging.getLogger("slamkit.runner")

#: Linux's largest nice value.
MAX_NICE = 19


def lower_thread_priority(niceness: int) -> bool:
    """Raise the calling thread's nice value by ``niceness`` (capped at 19); True if the OS applied it.

    Only the calling thread changes (Linux keeps one nice value per thread). Where per-thread priorities are not
    available (not Linux) nothing changes and False is returned.
    """
    if niceness <= 0:
        return False
    if not sys.platform.startswith("linux") or not hasattr(os, "setpriority"):
        log.debug("thread priorities are only set on Linux; %s keeps its priority", threading.current_thread().name)
        return False
    return _renice(threading.get_native_id(), niceness, threading.current_thread().name)


def lower_process_priority(pid: int, niceness: int) -> bool:
    """Raise the nice value of process ``pid`` (all of its threads' base: a worker process serving background
    work) by ``niceness``; True if applied."""
    if niceness <= 0 or not hasattr(os, "setpriority"):
        return False
    return _renice(pid, niceness, f"process {pid}")


def _renice(who: int, niceness: int, label: str) -> bool:
    """Raise the nice value of thread/process id ``who`` by ``niceness`` (capped at 19); False if refused."""
    try:
        current = os.getpriority(os.PRIO_PROCESS, who)
        os.setpriority(os.PRIO_PROCESS, who, min(MAX_NICE, current + niceness))
    except OSError as exc:  # e.g. a seccomp sandbox refusing setpriority: run on at the normal priority
        log.warning("could not lower the priority of %s: %s", label, exc)
        return False
    return True


@contextlib.contextmanager
def gil_switch_interval(seconds: float | None) -> Iterator[None]:
    """Use ``seconds`` as the interpreter's GIL switch interval inside the block (None: leave it), then restore
    the previous value."""
    if seconds is None:
        yield
        return
    if not seconds > 0:
        raise ValueError(f"GIL switch interval must be > 0 s, got {seconds}")
    previous = sys.getswitchinterval()
    sys.setswitchinterval(seconds)
    try:
        yield
    finally:
        sys.setswitchinterval(previous)
