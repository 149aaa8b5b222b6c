"""FrameSource: plays a dataset to the tracking thread from a thread of its own, like a camera driver.

Two modes. As fast as possible: every frame is delivered, in order, through a short bounded queue (the next
frames are read or rendered while tracking works on the current one). Real time: each frame is released at its
own timestamp (scaled by ``speed``) into a one-slot mailbox; a frame still in the mailbox when the next one
arrives is replaced and counted as dropped, as a live camera's frames are when tracking is busy. The source itself
keeps the camera's clock: its own work on a frame (the features extracted ahead) may run past the next frames'
times, which then wait in the camera's buffer of ``camera_buffer`` frames (a V4L2 device opened by OpenCV queues 4);
a frame the camera has replaced by the time the source is free again (``camera_buffer`` newer frames were due) is
dropped unprepared, so the source's lateness stays bounded (reading a file is the camera's part, not counted). A live
source
(``dataset=camera``: :func:`is_live`) is real time by nature: it is read continuously into the mailbox, paced by
the device itself (or, for a file played as a stream, at its timestamps: the dataset's ``paced``), and has no
length (:func:`frame_count` is None).
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


def is_live(dataset: object) -> bool:
    """Whether ``dataset`` is a live source (a capture device or stream, ``live = True``): real time by nature, no
    length, no ground truth."""
    return bool(getattr(dataset, "live", False))


def frame_count(dataset: Dataset) -> int | None:
    """The number of frames the dataset will deliver, or None for a live source (its ``len`` is unknown)."""
    return None if is_live(dataset) else len(dataset)


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

#: Paced real time: the frames a camera holds while the source is busy (OpenCV's V4L2 capture requests 4 buffers:
#: DEFAULT_V4L_BUFFERS in modules/videoio/src/cap_v4l.cpp); runner.realtime_camera_buffer.
CAMERA_BUFFER_FRAMES = 4


class EndOfSequence:
    """Marker delivered after the last frame."""


END = EndOfSequence()


class FrameSource(threading.Thread):
    """Delivers FrameData to ``get()``; ``frames_dropped`` counts frames replaced unseen or reached late (real time
    only; ``frames_late`` of them late) and ``dropped`` lists them as (frame index, timestamp s).

    frames: the dataset (iterated once, in this thread; an iterator with ``close()``, a generator, is closed here
    when the source ends, so a capture device is released by the thread that reads it). realtime: one-slot
    mailbox, newest frame wins. paced: in real time, release each frame at its timestamp (False: as soon as it is
    read, for a live device that delivers frames at its own rate). speed: playback rate factor for paced real time
    (2.0 plays twice as fast). on_fault: called if reading raises. prepare: called in this thread on each frame read
    (in real time: released), before it is queued (the threaded runner's feature extraction ahead:
    slamkit/runtime/extract_ahead.py). ahead: as fast as possible, the frames queued ahead of tracking.
    camera_buffer: paced real time, the frames the camera holds for the source while it is busy preparing one
    (module docstring); an older one is replaced, dropped unprepared, and counted in ``frames_late``.
    """

    def __init__(
        self,
        frames: Iterable[FrameData],
        realtime: bool,
        on_fault: Callable[[ThreadFault], None],
        speed: float = 1.0,
        paced: bool = True,
        prepare: Callable[[FrameData], None] | None = None,
        ahead: int = PREFETCH_FRAMES,
        camera_buffer: int = CAMERA_BUFFER_FRAMES,
    ) -> None:
        super().__init__(name="frame-source", daemon=True)
        if speed <= 0:
            raise ValueError(f"playback speed must be > 0, got {speed}")
        if ahead < 1:
            raise ValueError(f"frames read ahead must be >= 1, got {ahead}")
        if camera_buffer < 1:
            raise ConfigError(f"runner.realtime_camera_buffer = {camera_buffer}: expected a number of frames >= 1")
        self.camera_buffer = int(camera_buffer)
        self._prepare = prepare
        self.ahead = ahead
        self._frames = frames
        self.realtime = realtime
        self.paced = paced
        self.speed = speed
        self._on_fault = on_fault
        self._cond = threading.Condition()
        self._slots: deque[FrameData | EndOfSequence] = deque()
        self._stop_requested = False
        self._interrupted = False
        self.frames_read = 0
        self.frames_dropped = 0
        self.dropped: list[tuple[int, float]] = []
        self._busy_until = 0.0  # paced real time: see run()
        self.frames_late = 0  # of frames_dropped: replaced in the camera's buffer while the source was busy
        self.first_timestamp_s: float | None = None
        self.last_timestamp_s: float | None = None
        self.fault: ThreadFault | None = None

    @property
    def stopping(self) -> bool:
        """Whether ``stop()`` was called."""
        return self._stop_requested

    def stop(self) -> None:
        """No more frames: ``get()`` returns what the mailbox / queue holds, then None; the thread ends at its next
        frame."""
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
                        old = self._slots.popleft()
                        assert isinstance(old, FrameData)
                        self.frames_dropped += 1
                        self.dropped.append((old.index, old.timestamp_s))
            else:
                self._cond.wait_for(lambda: len(self._slots) < self.ahead or self._stop_requested)
            if self._stop_requested:
                return False
            self._slots.append(item)
            self._cond.notify_all()
            return True

    def _deliver(self, data: FrameData, due: float | None) -> bool:
        """Prepare ``data`` and queue it (False: stopped meanwhile). due: its release time (paced real time), from
        which the source's work on it is counted on the camera's clock (``_busy_until``)."""
        work_start = time.perf_counter()
        if self._prepare is not None:
            self._prepare(data)
        if not self._put(data):
            return False
        if due is not None:
            self._busy_until = max(due, self._busy_until) + (time.perf_counter() - work_start)
        return True

    def _drop_late(self, data: FrameData) -> None:
        """Count ``data`` as dropped without preparing or queueing it (real time: the camera replaced it)."""
        with self._cond:
            self.frames_dropped += 1
            self.frames_late += 1
            self.dropped.append((data.index, data.timestamp_s))

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
        frames: Iterator[FrameData] | None = None
        try:
            start = time.perf_counter()
            frames = iter(self._frames)
            previous_due: float | None = None
            # paced real time: when the source's own work on the frames it took (preparing, queueing) ended, on
            # the camera's clock; reading a frame is the camera's part and not counted, so the time spent reading
            # the frames dropped here never makes the source later
            self._busy_until = start
            # the newest frame the source met after the camera had replaced it: dropped once a newer frame is read;
            # the stream's last frame is never replaced, so it is delivered
            replaced: FrameData | None = None
            for data in frames:
                if self.first_timestamp_s is None:
                    self.first_timestamp_s = data.timestamp_s
                self.last_timestamp_s = data.timestamp_s
                self.frames_read += 1
                if replaced is not None:
                    self._drop_late(replaced)
                    replaced = None
                due: float | None = None
                if self.realtime and self.paced:
                    due = start + (data.timestamp_s - self.first_timestamp_s) / self.speed
                    # the camera_buffer-th frame after this one is due that many frame intervals after it (the last
                    # interval: later timestamps are not read yet); free only after that, the source meets a frame
                    # the camera has already replaced
                    late = previous_due is not None and self._busy_until >= due + self.camera_buffer * max(
                        due - previous_due, 0.0
                    )
                    previous_due = due
                    if late:
                        replaced = data
                        continue
                    if not self._wait_until(due):
                        return
                if not self._deliver(data, due):
                    return
            if replaced is not None and not self._deliver(replaced, None):
                return
            self._put(END)
        except BaseException as exc:  # reported, never a silently dead thread
            self.fault = ThreadFault(self.name, exc, traceback.format_exc())
            self._on_fault(self.fault)
            # the frames already delivered are good: tracking finishes them, then meets the end
            self._put(END)
        finally:
            close = getattr(frames, "close", None)
            if callable(close):
                try:
                    close()
                except Exception as exc:  # releasing the source must not hide how the run ended
                    log.warning("the frame source could not be closed: %s", exc)
