"""Scheduling of the threaded runner's background threads (slamkit/runtime/priority.py)."""

from __future__ import annotations

import os
import sys
import threading

import pytest

from slamkit.app import build_runner
from slamkit.config import compose_config
from slamkit.errors import ConfigError
from slamkit.runtime.priority import MAX_NICE, gil_switch_interval, lower_thread_priority
from slamkit.runtime.workers import PipelineWorker, ThreadFault

linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread nice values are Linux's")


def _own_nice() -> int:
    return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())


@linux_only
def test_a_worker_lowers_only_its_own_threads_priority() -> None:
    seen: list[int] = []
    faults: list[ThreadFault] = []
    main_before = _own_nice()
    worker: PipelineWorker[int] = PipelineWorker(
        "background", lambda item, abort: seen.append(_own_nice()), faults.append, 7
    )
    worker.start()
    worker.submit(1)
    worker.stop(drain=True)
    worker.join(timeout=10)
    assert not faults and worker.priority_lowered
    assert seen == [min(MAX_NICE, main_before + 7)]
    assert _own_nice() == main_before  # the calling thread keeps its priority


@linux_only
def test_niceness_is_capped_at_19_and_zero_changes_nothing() -> None:
    out: dict[str, object] = {}

    def body() -> None:
        out["zero"] = lower_thread_priority(0)
        out["after_zero"] = _own_nice()
        out["big"] = lower_thread_priority(100)
        out["after_big"] = _own_nice()

    before = _own_nice()
    t = threading.Thread(target=body)
    t.start()
    t.join()
    assert out == {"zero": False, "after_zero": before, "big": True, "after_big": MAX_NICE}


@linux_only
@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="no SCHED_IDLE")
def test_a_thread_the_nice_cap_leaves_beside_its_creator_goes_to_the_idle_class() -> None:
    """Under ``nice -n 19`` raising the nice value changes nothing: the background thread must still yield to
    tracking, so it is put in SCHED_IDLE; a thread the cap leaves well below its creator stays SCHED_OTHER."""
    out: dict[str, int] = {}

    def body(niceness_first: int) -> None:
        tid = threading.get_native_id()
        start = _own_nice()
        out["first"] = lower_thread_priority(niceness_first)
        out["gap_first"] = _own_nice() - start
        out["policy_first"] = os.sched_getscheduler(tid)
        out["second"] = lower_thread_priority(10)  # at 19 now: no nice level left
        out["policy_second"] = os.sched_getscheduler(tid)

    t = threading.Thread(target=body, args=(100,))
    t.start()
    t.join()
    assert out["first"] and out["second"]
    assert out["policy_second"] == os.SCHED_IDLE
    if out["gap_first"] >= 5:  # the process runs at nice <= 14: the first raise was a real one
        assert out["policy_first"] == os.SCHED_OTHER
    else:
        assert out["policy_first"] == os.SCHED_IDLE
    assert os.sched_getscheduler(threading.get_native_id()) == os.SCHED_OTHER  # the caller keeps its class


def test_the_switch_interval_is_restored_after_the_block_even_on_error() -> None:
    before = sys.getswitchinterval()
    with pytest.raises(RuntimeError), gil_switch_interval(2e-4):
        assert sys.getswitchinterval() == pytest.approx(2e-4)
        raise RuntimeError("boom")
    assert sys.getswitchinterval() == before
    with gil_switch_interval(None):
        assert sys.getswitchinterval() == before
    with pytest.raises(ValueError, match="> 0"), gil_switch_interval(0.0):
        pass


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("runner.background_niceness=-1", r"runner.background_niceness = -1: expected an integer in \[0, 19\]"),
        ("runner.background_niceness=2.5", r"runner.background_niceness = 2.5"),
        ("runner.gil_switch_interval_ms=0", r"runner.gil_switch_interval_ms = 0: expected a number in \(0, 100\]"),
    ],
)
def test_bad_scheduling_settings_name_the_key(override: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        build_runner(compose_config(["runner=threaded", override]))
