"""A phase-fair readers-writer lock: many readers or one writer; neither side starves the other."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager


class ReadWriteLock:
    """One lock per map (see DESIGN section 4). ``read()`` and ``write()`` are context managers.

    Phase-fair: a writer waiting blocks new readers, so local mapping's commits and loop correction are not
    starved by tracking's frequent reads; and when a writer releases the lock, the readers already waiting
    go in before the next writer, so a writer taking the lock again and again (local mapping fuses a keyframe's
    points into ~25 neighbours, one short write each) does not hold tracking off for the whole series. Without
    the hand-over the writing thread, which still holds the GIL when it releases, re-took the lock before the
    woken reader ran: tracking waited up to 70 ms for its read lock in real-time runs of the synthetic room.
    Reads are re-entrant: a thread holding the read lock may take it again (tracking holds it for the whole of a
    frame, as ORB-SLAM's Tracking::Track holds mMutexMapUpdate, and the steps inside take it too); a nested read
    does not wait for a waiting writer, which would wait for the outer read: a deadlock. Writes are not
    re-entrant: a thread holding the write lock must not take it again, nor a read.
    """

    def __init__(self) -> None:
        self._cond = threading.Condition(threading.Lock())
        self._readers = 0
        self._readers_waiting = 0
        self._writer = False
        self._writers_waiting = 0
        # True from a writer's release (with readers waiting) until those readers are done: a read phase
        # that writers wait out.
        self._read_turn = False
        self._held = threading.local()  # .depth: how many reads this thread holds (re-entrant reads)
        self._writes = 0  # write locks released so far

    @property
    def writes(self) -> int:
        """How many times the write lock was released so far: a reader comparing it before and after a gap sees
        whether anyone wrote in between (see slamkit.pipeline.loop_correction.read_then_write)."""
        return self._writes

    @contextmanager
    def read(self) -> Iterator[None]:
        depth = getattr(self._held, "depth", 0)
        if depth:  # this thread already reads: no wait (a writer waiting for the outer read would deadlock)
            self._held.depth = depth + 1
            try:
                yield
            finally:
                self._held.depth = depth
            return
        with self._cond:
            self._readers_waiting += 1
            try:
                while self._writer or (self._writers_waiting and not self._read_turn):
                    self._cond.wait()
            except BaseException:  # interrupted while waiting: a read phase must not wait for this reader
                if self._readers == 0 and self._readers_waiting == 1:
                    self._read_turn = False
                    self._cond.notify_all()
                raise
            finally:
                self._readers_waiting -= 1
            self._readers += 1
        self._held.depth = 1
        try:
            yield
        finally:
            self._held.depth = 0
            with self._cond:
                self._readers -= 1
                if self._readers == 0:
                    self._read_turn = False
                    self._cond.notify_all()

    @contextmanager
    def write(self) -> Iterator[None]:
        with self._cond:
            self._writers_waiting += 1
            try:
                while self._writer or self._readers or self._read_turn:
                    self._cond.wait()
            finally:
                self._writers_waiting -= 1
            self._writer = True
        try:
            yield
        finally:
            with self._cond:
                self._writer = False
                self._writes += 1
                self._read_turn = self._readers_waiting > 0
                self._cond.notify_all()
