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
