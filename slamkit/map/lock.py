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
    Not re-entrant: a thread holding the write lock must not take it again.
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

    @contextmanager
    def read(self) -> Iterator[None]:
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
        try:
            yield
        finally:
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
                self._read_turn = self._readers_waiting > 0
                self._cond.notify_all()
