"""PipelineWorker and FrameSource: ordering, pausing at safe points, abort, faults, real-time dropping."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from concurrent.futures import Future

import numpy as np
import pytest

from slamkit.errors import ConfigError
from slamkit.runtime.source import END, FrameSource
from slamkit.runtime.workers import PipelineThreadError, PipelineWorker, ThreadFault
from slamkit.sensors import FrameData

pytestmark = pytest.mark.timeout(60)


def _delivered(src: FrameSource) -> list[int]:
    """Start ``src`` and take every frame it delivers, at once, until the end; their indices in order."""
    src.start()
    got = []
    while True:
        item = src.get(timeout_s=5)
        if item is END:
            return got
        assert isinstance(item, FrameData)
        got.append(item.index)


def _frames(n: int, fps: float) -> list[FrameData]:
    img = np.zeros((4, 4), np.uint8)
    return [FrameData(index=i, timestamp_s=i / fps, image=img) for i in range(n)]


def test_worker_processes_items_in_order_and_drains_before_stopping() -> None:
    seen: list[int] = []
    faults: list[ThreadFault] = []
    worker: PipelineWorker[int] = PipelineWorker("w", lambda item, abort: seen.append(item), faults.append)
    worker.start()
    for i in range(50):
        worker.submit(i)
    worker.stop(drain=True)
    worker.join(timeout=10)
    assert not worker.is_alive()
    assert seen == list(range(50)) and not faults


def test_pause_waits_for_the_current_item_and_aborts_it() -> None:
    started = threading.Event()
    aborted_seen: list[bool] = []

    def slow(item: int, abort: threading.Event) -> None:
        started.set()
        # an optimization loop that honours the abort token
        for _ in range(1000):
            if abort.is_set():
                aborted_seen.append(True)
                return
            time.sleep(0.005)
        aborted_seen.append(False)

    worker: PipelineWorker[int] = PipelineWorker("mapping", slow, lambda f: None)
    worker.start()
    worker.submit(1)
    assert started.wait(5)
    t0 = time.perf_counter()
    worker.pause().result(timeout=5)
    assert time.perf_counter() - t0 < 2.0  # the abort token cut the 5 s item short
    assert aborted_seen == [True]
    worker.submit(2)  # queued while parked: not started
    time.sleep(0.1)
    assert worker.pending() == 1 and len(aborted_seen) == 1
    worker.resume()
    worker.stop(drain=True)
    worker.join(timeout=10)
    assert len(aborted_seen) == 2 and aborted_seen[1] is False


def test_a_raising_item_reports_the_thread_name_and_traceback_and_fails_pausers() -> None:
    faults: list[ThreadFault] = []
    gate = threading.Event()

    def boom(item: int, abort: threading.Event) -> None:
        gate.wait(5)
        raise ValueError(f"bad item {item}")

    worker: PipelineWorker[int] = PipelineWorker("loop-closing", boom, faults.append)
    worker.start()
    worker.submit(7)
    time.sleep(0.05)
    fut: Future[None] = worker.pause()
    gate.set()
    worker.join(timeout=5)
    assert not worker.is_alive()
    assert len(faults) == 1 and faults[0].thread_name == "loop-closing"
    assert "bad item 7" in faults[0].formatted_traceback and "boom" in faults[0].formatted_traceback
    with pytest.raises(PipelineThreadError, match="loop-closing thread failed: ValueError: bad item 7"):
        fut.result(timeout=1)


def test_fast_source_delivers_every_frame_in_order_then_end() -> None:
    src = FrameSource(_frames(20, 30.0), realtime=False, on_fault=lambda f: None)
    got = _delivered(src)
    assert got == list(range(20)) and src.frames_dropped == 0


def test_realtime_source_drops_frames_a_busy_consumer_misses() -> None:
    """100 frames at 200 Hz (0.5 s) to a consumer that needs 20 ms per frame: it can take about a quarter."""
    src = FrameSource(_frames(100, 200.0), realtime=True, on_fault=lambda f: None)
    src.start()
    got = []
    while True:
        item = src.get(timeout_s=5)
        if item is END:
            break
        assert isinstance(item, FrameData)
        got.append(item.index)
        time.sleep(0.02)
    assert got == sorted(got) and got[-1] >= 95  # always the newest frame
    assert len(got) + src.frames_dropped == 100
    assert 50 <= src.frames_dropped <= 95


@pytest.mark.parametrize("realtime", [False, True])
def test_the_source_prepares_each_frame_in_its_thread_before_delivering_it(realtime: bool) -> None:
    """``prepare`` (the threaded runner's extraction ahead) runs in the source thread on every frame read, before the
    frame is queued (as fast as possible: at most ``ahead`` queued; real time: before the mailbox)."""
    prepared: dict[int, str] = {}
    queued: list[int] = []

    def prepare(data: FrameData) -> None:
        prepared[data.index] = threading.current_thread().name

    # 100 Hz: preparing a frame (here: nothing) never makes the real-time source miss the next frame's time
    src = FrameSource(_frames(30, 100.0), realtime=realtime, on_fault=lambda f: None, prepare=prepare, ahead=6)
    src.start()
    while True:
        item = src.get(timeout_s=5)
        if item is END:
            break
        assert isinstance(item, FrameData) and item.index in prepared  # prepared before it was delivered
        queued.append(len(src._slots))
        time.sleep(0.005)
    assert set(prepared) == set(range(30)) and set(prepared.values()) == {"frame-source"}
    assert max(queued) <= (1 if realtime else 6)
    with pytest.raises(ValueError, match="ahead"):
        FrameSource(_frames(1, 30.0), realtime=False, on_fault=lambda f: None, ahead=0)


@pytest.mark.parametrize("camera_buffer", [1, 2, 4])
def test_a_realtime_source_late_from_its_own_work_drops_the_frames_the_camera_replaced_meanwhile(
    camera_buffer: int,
) -> None:
    """Frames at 25 Hz (40 ms apart). Preparing frame 3 (due at 120 ms) takes 130 ms, to 250 ms. A camera holding one
    frame has replaced 4 and 5 by then (the frames after them were due at 200 and 240 ms): the source drops them
    unprepared and takes 6, so its lateness is not carried on. Holding two, only 4 is replaced (6 was due at 240 ms);
    holding four, none. Frames 8 and 9 take 60 ms each to read: reading is the camera's part, so no frame is dropped
    for it. Preparing frame 10 takes 130 ms too, but nothing replaces the stream's last frame, 11: it is delivered."""
    prepared: list[int] = []

    def prepare(data: FrameData) -> None:
        prepared.append(data.index)
        if data.index in (3, 10):
            time.sleep(0.13)

    def slow_reads() -> Iterator[FrameData]:
        for frame in _frames(12, 25.0):
            if frame.index in (8, 9):
                time.sleep(0.06)
            yield frame

    src = FrameSource(
        slow_reads(), realtime=True, on_fault=lambda f: None, prepare=prepare, camera_buffer=camera_buffer
    )
    got = _delivered(src)
    # every frame but 4 and 5 was prepared and queued (a queued frame the consumer is too slow to take before the
    # next one is replaced in the mailbox, as before: counted in frames_dropped, not in frames_late)
    replaced = {1: [4, 5], 2: [4], 4: []}[camera_buffer]
    assert prepared == [i for i in range(12) if i not in replaced] and src.frames_late == len(replaced)
    assert set(replaced) <= {index for index, _ in src.dropped} and len(got) + src.frames_dropped == 12
    with pytest.raises(ConfigError, match=r"runner\.realtime_camera_buffer"):
        FrameSource(_frames(1, 30.0), realtime=True, on_fault=lambda f: None, camera_buffer=0)


def test_live_source_is_read_continuously_newest_frame_wins_and_is_closed_at_the_end() -> None:
    """A live device paces itself (paced=False): frames go into the mailbox as they are read, a consumer slower
    than the device gets the newest, the dropped ones are listed with their timestamps, and the source (a
    generator: a capture) is closed by the source thread when it stops."""
    closed = threading.Event()

    def device():  # type: ignore[no-untyped-def]
        try:
            for frame in _frames(1000, 30.0):
                time.sleep(0.002)  # a 500 Hz device, stamped at 30 Hz: paced, this would take 33 s
                yield frame
        finally:
            closed.set()

    src = FrameSource(device(), realtime=True, on_fault=lambda f: None, paced=False)
    src.start()
    got = []
    while len(got) < 10:
        item = src.get(timeout_s=5)
        assert isinstance(item, FrameData)
        got.append(item.index)
        time.sleep(0.02)
    src.stop()
    assert closed.wait(timeout=5) and src.frames_dropped > 0
    assert got == sorted(got) and got[-1] > 40  # far beyond the 10th frame: never stale ones
    assert len(src.dropped) == src.frames_dropped
    assert all(t == pytest.approx(i / 30.0) for i, t in src.dropped) and not set(got) & {i for i, _ in src.dropped}


def test_a_failing_source_reports_its_fault() -> None:
    def frames():  # type: ignore[no-untyped-def]
        yield from _frames(3, 30.0)
        raise OSError("cannot read frame 3: /data/img003.png")

    faults: list[ThreadFault] = []
    src = FrameSource(frames(), realtime=False, on_fault=faults.append)
    src.start()
    src.join(timeout=5)
    assert faults and faults[0].thread_name == "frame-source" and "img003.png" in str(faults[0].exc)


def test_ctrl_c_wrapped_by_a_callback_from_compiled_code_is_recognised() -> None:
    """Ctrl-C handled inside a callback from compiled code reaches the caller as a SystemError whose cause chain
    holds the KeyboardInterrupt (seen with numba's unpickling callback); the runners treat it as Ctrl-C."""
    from slamkit.runtime.workers import raised_by_ctrl_c

    def wrapped() -> SystemError:
        try:
            try:
                raise KeyboardInterrupt
            except KeyboardInterrupt as inner:
                raise SystemError("<function _numba_unpickle> returned a result with an exception set") from inner
        except SystemError as outer:
            try:
                raise SystemError("CPUDispatcher(<function kernel>) returned a result with an exception set") from outer
            except SystemError as top:
                return top

    assert raised_by_ctrl_c(wrapped())
    assert raised_by_ctrl_c(KeyboardInterrupt())
    assert not raised_by_ctrl_c(SystemError("a real failure"))
    plain = ValueError("bad input")
    plain.__context__ = RuntimeError("while handling this")
    assert not raised_by_ctrl_c(plain)
    looped = ValueError("a")
    looped.__cause__ = looped  # a cycle in the chain ends the walk
    assert not raised_by_ctrl_c(looped)
