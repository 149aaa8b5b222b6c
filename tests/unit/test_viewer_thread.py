"""The viewer's thread (plugins/slamkit_rerun/worker.py): events are drawn in the order they came; a frame with newer
frames waiting is drawn stale (no image) when stale frames are skipped, never otherwise; keyframe-like events are
never stale; the first failure is reported once and drops what follows."""

from __future__ import annotations

import threading

from slamkit_rerun.worker import ViewerThread


def fill_behind_a_blocked_job(thread: ViewerThread, drawn: list[tuple[str, bool]]) -> None:
    """Queue: a job that blocks until the rest is queued, then frames 0-2 with a keyframe between 1 and 2."""
    release = threading.Event()

    def block(stale: bool) -> None:
        release.wait(5.0)
        drawn.append(("block", stale))

    thread.submit(block)
    for name, is_frame in (("f0", True), ("f1", True), ("kf", False), ("f2", True)):
        thread.submit(lambda stale, n=name: drawn.append((n, stale)), is_frame=is_frame)
    release.set()


def test_a_thread_that_fell_behind_draws_only_the_latest_frame_in_full() -> None:
    drawn: list[tuple[str, bool]] = []
    thread = ViewerThread("t", skip_stale_frames=True, on_error=lambda exc: None)
    fill_behind_a_blocked_job(thread, drawn)
    assert thread.close(5.0)
    assert drawn == [("block", False), ("f0", True), ("f1", True), ("kf", False), ("f2", False)]
    assert thread.frames_skipped == 2


def test_without_skipping_every_frame_is_drawn_in_full() -> None:
    drawn: list[tuple[str, bool]] = []
    thread = ViewerThread("t", skip_stale_frames=False, on_error=lambda exc: None)
    fill_behind_a_blocked_job(thread, drawn)
    assert thread.close(5.0)
    assert [stale for _, stale in drawn] == [False] * 5
    assert thread.frames_skipped == 0


def test_the_first_failure_is_reported_once_and_the_rest_is_dropped() -> None:
    errors: list[BaseException] = []
    drawn: list[int] = []

    def draw(i: int) -> None:
        if i == 3:
            raise RuntimeError("display went away")
        drawn.append(i)

    thread = ViewerThread("t", skip_stale_frames=False, on_error=errors.append)
    for i in range(10):
        thread.submit(lambda stale, i=i: draw(i), is_frame=True)
    assert thread.close(5.0)
    thread.submit(lambda stale: drawn.append(99))  # after the failure: ignored
    assert drawn == [0, 1, 2]
    assert [str(e) for e in errors] == ["display went away"] and thread.failed
