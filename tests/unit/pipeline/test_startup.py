"""slamkit.pipeline.startup: cached kernels loaded before a run (never compiled there) and the start-up heap frozen."""

from __future__ import annotations

import gc
import json
import subprocess
import sys
import textwrap
from pathlib import Path

from slamkit.pipeline.startup import freeze_startup_heap, thaw_startup_heap

KERNELS = """
import numba
import numpy as np


@numba.njit(cache=True)
def called(x):
    return x.sum() * {factor}


@numba.njit(cache=True)
def never_called(x):
    return x.max()
"""

PROBE = """
import json, sys
sys.path.insert(0, sys.argv[1])
import numpy as np
import kernels_under_test as mod
from slamkit.pipeline.startup import load_cached_kernels
if sys.argv[2] == "call":
    mod.called(np.arange(3.0))
    print(json.dumps({}))
else:
    done = load_cached_kernels([mod])
    print(json.dumps({
        "loaded": done.loaded,
        "kernels": done.kernels,
        "called_overloads": len(mod.called.overloads),
        "never_called_overloads": len(mod.never_called.overloads),
        "misses": sum(mod.called._cache_misses.values()),
        "result": float(mod.called(np.arange(3.0))) if mod.called.overloads else None,
        "misses_after_call": sum(mod.called._cache_misses.values()),
    }))
"""


def _probe(tmp_path: Path, mode: str) -> dict[str, object]:
    out = subprocess.run(
        [sys.executable, "-c", PROBE, str(tmp_path), mode], capture_output=True, text=True, check=True, timeout=240
    )
    result: dict[str, object] = json.loads(out.stdout.strip().splitlines()[-1])
    return result


def test_load_cached_kernels_loads_what_the_cache_holds_and_compiles_nothing(tmp_path: Path) -> None:
    source = tmp_path / "kernels_under_test.py"
    source.write_text(textwrap.dedent(KERNELS.format(factor=2.0)))
    _probe(tmp_path, "call")  # a first run compiles ``called`` for float64 arrays and writes numba's disk cache
    fresh = _probe(tmp_path, "load")
    # the cached signature is loaded before any call; the kernel never called has nothing cached, nothing compiled
    assert fresh["loaded"] == 1 and fresh["kernels"] == 1
    assert fresh["called_overloads"] == 1 and fresh["never_called_overloads"] == 0
    assert fresh["misses"] == 0 and fresh["misses_after_call"] == 0  # the call used the loaded code
    assert fresh["result"] == 6.0
    # the kernel's code changed: its cache no longer matches, and nothing is loaded (nor compiled) for it
    source.write_text(textwrap.dedent(KERNELS.format(factor=3.0)))
    stale = _probe(tmp_path, "load")
    assert stale["loaded"] == 0 and stale["called_overloads"] == 0 and stale["result"] is None


def test_freeze_startup_heap_moves_live_objects_out_of_collections() -> None:
    class Node:
        pass

    before = Node()
    try:
        frozen = freeze_startup_heap()
        after = Node()
        tracked = {id(o) for o in gc.get_objects()}
        # Only > 0: the permanent generation's size moves with other threads of the test session between the call
        # and here (a freeze adds to it; an object freed by its last reference leaves it: CI saw +2, a full run -2)
        assert frozen > 0 and gc.get_freeze_count() > 0
        assert id(before) not in tracked  # frozen: full collections no longer walk it
        assert id(after) in tracked  # objects made later are collected as usual
    finally:
        gc.unfreeze()


def test_thaw_gives_back_what_the_warm_up_froze_and_leaves_a_callers_own_freeze_alone() -> None:
    class Node:
        pass

    try:
        assert thaw_startup_heap() == 0  # nothing frozen here: nothing to give back
        gc.freeze()  # the caller's own freeze
        assert thaw_startup_heap() == 0 and gc.get_freeze_count() > 0
        gc.unfreeze()
        frozen = Node()
        assert freeze_startup_heap() > 0
        assert id(frozen) not in {id(o) for o in gc.get_objects()}
        assert thaw_startup_heap() > 0
        assert gc.get_freeze_count() == 0
        assert id(frozen) in {id(o) for o in gc.get_objects()}  # collected as usual again
        assert thaw_startup_heap() == 0
    finally:
        gc.unfreeze()
