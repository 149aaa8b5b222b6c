"""slamkit.thread_budget: the single-threaded hint holds inside its block, in the thread that entered it only."""

from __future__ import annotations

import threading

from slamkit.thread_budget import is_single_threaded, single_threaded


def test_the_hint_holds_inside_nested_blocks_and_ends_with_the_outer_one() -> None:
    assert not is_single_threaded()
    with single_threaded():
        assert is_single_threaded()
        with single_threaded():
            assert is_single_threaded()
        assert is_single_threaded()  # the inner block's end leaves the outer one's hint
    assert not is_single_threaded()


def test_the_hint_is_the_entering_threads_only() -> None:
    seen: list[bool] = []
    with single_threaded():
        other = threading.Thread(target=lambda: seen.append(is_single_threaded()))
        other.start()
        other.join()
        assert is_single_threaded()
    assert seen == [False]


def test_the_hint_ends_when_the_block_raises() -> None:
    try:
        with single_threaded():
            raise RuntimeError("boom")
    except RuntimeError:
        pass
    assert not is_single_threaded()
