"""FrameSource: plays a dataset to the tracking thread from a thread of its own, like a camera driver.

Two modes. As fast as possible: every frame is delivered, in order, through a short bounded queue (the next
frames are read or rendered while tracking works on the current one). Real time: each frame is released at its
own timestamp (scaled by ``speed``) into a one-slot mailbox; a frame still in the mailbox when the next one
arrives is replaced and counted as dropped, as a live camera's frames are when tracking is busy.
"""

from __future__ import annotations

import logging
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from typing import Protocol, cast

from slamkit.errors import ConfigError, FrameReadError
from slamkit.interfaces import Dataset
from slamkit.runtime.workers import ThreadFault
from slamkit.sensors import FrameData

log = logging.getLogger("slamkit.io")

#: What a run does with a frame whose file is missing, undecodable or damaged (``runner.bad_frames``)
BAD_FRAME_POLICIES = ("skip", "stop")


def check_bad_frames_policy(policy: str) -> str:
    """``policy`` if it is one of BAD_FRAME_POLICIES, else a ConfigError naming ``runner.bad_frames``."""
    if policy not in BAD_FRAME_POLICIES:
        raise ConfigError(f"runner.bad_frames = {policy!r}: expected one of {', '.join(BAD_FRAME_POLICIES)}")
    return policy


class IndexedFrames(Protocol):
    """A dataset whose frames can be read one by one by number (every SequenceDataset of slamkit.io)."""

    def __len__(self) -> int: ...

    def __getitem__(self, i: int) -> FrameData: ...


def readable_frames(
    dataset: Dataset, policy: str, on_skip: Callable[[int, str], None] | None = None
) -> Iterable[FrameData]:
    """The dataset's frames in order; with ``policy`` "skip" a frame that cannot be read (FrameReadError: a
    missing, undecodable or truncated image) is logged, reported to ``on_skip(frame_index, reason)`` and left
    out, and the sequence goes on; with "stop" the error ends the iteration. The frames after a skipped one keep
    their numbers (a gap, as a dropped camera frame leaves). A dataset that cannot be read by number is iterated
    as it is."""
    check_bad_frames_policy(policy)
    # looked up on the type, as ``dataset[i]`` does (a wrapper that delegates attributes is not subscriptable)
    indexed = all(hasattr(type(dataset), name) for name in ("__getitem__", "__len__"))
    if policy == "stop" or not indexed:
        return dataset
    return _skipping_unreadable(cast(IndexedFrames, dataset), on_skip)


def _skipping_unreadable(dataset: IndexedFrames, on_skip: Callable[[int, str], None] | None) -> Iterator[FrameData]:
    for i in range(len(dataset)):
        try:
            frame = dataset[i]
        except FrameReadError as exc:
            log.warning("frame %d skipped: %s", i, exc)
            if on_skip is not None:
                on_skip(i, str(exc))
            continue
        yield frame


#: Frames read ahead in as-fast-as-possible mode.
PREFETCH_FRAMES = 4


class EndOfSequence:
    """Marker delivered after the last frame."""


END = EndOfSequence()


class FrameSource(threading.Thread):
    """Delivers FrameData to ``get()``; ``frames_dropped`` counts frames replaced unseen (real time only).

    frames: the dataset (iterated once, in this thread). realtime: release frames at their timestamps.
    speed: playback rate factor for real time (2.0 plays twice as fast). on_fault: called if reading raises.
    """

    def __init__(
        self,
        frames: Iterable[FrameData],
        realtime: bool,
        on_fault: Callable[[ThreadFault], None],
        speed: float = 1.0,
    ) -> None:
        super().__init__(name="frame-source", daemon=True)
        if speed <= 0:
            raise ValueError(f"playback speed must be > 0, got {speed}")
        self._frames = frames
        self.realtime = realtime
        self.speed = speed
        self._on_fault = on_fault
        self._cond = threading.Condition()
        self._slots: deque[FrameData | EndOfSequence] = deque()
        self._stop_requested = False
        self._interrupted = False
        self.frames_read = 0
        self.frames_dropped = 0
        self.first_timestamp_s: float | None = None
        self.last_timestamp_s: float | None = None
        self.fault: ThreadFault | None = None

    def stop(self) -> None:
        with self._cond:
            self._stop_requested = True
            self._cond.notify_all()

    def get(self, timeout_s: float | None = None) -> FrameData | EndOfSequence | None:
        """The next frame (real time: the newest), END after the last one, or None on timeout / stop."""
        with self._cond:
            ok = self._cond.wait_for(
                lambda: bool(self._slots) or self._stop_requested or self._interrupted, timeout=timeout_s
            )
            if not ok or not self._slots or self._interrupted:
                return None
            item = self._slots.popleft()
            self._cond.notify_all()
            return item

    def interrupt(self) -> None:
        """Make ``get()`` return None from now on (a pipeline thread failed: tracking must stop)."""
        with self._cond:
            self._interrupted = True
            self._cond.notify_all()

    def _put(self, item: FrameData | EndOfSequence) -> bool:
        with self._cond:
            if self.realtime:
                if isinstance(item, FrameData):
                    # the camera does not wait: an untaken frame is replaced by the newer one
                    while self._slots and isinstance(self._slots[0], FrameData):
                        self._slots.popleft()
                        self.frames_dropped += 1
            else:
                self._cond.wait_for(lambda: len(self._slots) < PREFETCH_FRAMES or self._stop_requested)
            if self._stop_requested:
                return False
            self._slots.append(item)
            self._cond.notify_all()
            return True

    def _wait_until(self, deadline: float) -> bool:
        """Sleep until the perf_counter time ``deadline`` (returns False when stopped meanwhile)."""
        with self._cond:
            while not self._stop_requested:
                left = deadline - time.perf_counter()
                if left <= 0:
                    return True
                self._cond.wait(timeout=left)
            return False

    def run(self) -> None:
        try:
            start = time.perf_counter()
            for data in self._frames:
                if self.first_timestamp_s is None:
                    self.first_timestamp_s = data.timestamp_s
                if self.realtime:
                    due = start + (data.timestamp_s - self.first_timestamp_s) / self.speed
                    if not self._wait_until(due):
                        return
                self.last_timestamp_s = data.timestamp_s
                self.frames_read += 1
                if not self._put(data):
                    return
            self._put(END)
        except BaseException as exc:  # reported, never a silently dead thread
            self.fault = ThreadFault(self.name, exc, traceback.format_exc())
            self._on_fault(self.fault)
            # the frames already delivered are good: tracking finishes them, then meets the end
            self._put(END)
