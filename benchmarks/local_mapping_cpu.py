"""Local mapping's cost per keyframe in CPU time, for comparing two code versions on a loaded machine.

Usage: nice -n 19 python benchmarks/local_mapping_cpu.py OUT.json -- run runner=sequential seed=0 [overrides...]

Runs ``slamkit`` with the arguments after ``--`` (the sequential runner: local mapping runs in the main thread)
with local mapping's stage timers (``MappingOutcome.timings_ms``: insert, point culling, triangulation, fusion,
local BA, keyframe culling) reading the thread's CPU time (``time.thread_time``) instead of the wall clock, and
writes every keyframe's stage timings to OUT.json (a list of {stage: ms}), then prints each stage's median / mean
and the per-keyframe total. On a machine shared with other jobs the wall-clock medians of ``slamkit bench`` move by
1.5x between runs of the same code; CPU time does not count the time the process waits for a core (cache and
memory contention still show). The run's outputs (trajectory.tum, metrics.json) are written as by ``slamkit run``.
"""

from __future__ import annotations

import atexit
import json
import sys
import time
import types
from pathlib import Path
from typing import Any

import numpy as np

import slamkit.pipeline.local_mapping as local_mapping
from slamkit.cli import main as slamkit_main


def summarize(records: list[dict[str, float]]) -> str:
    """Per stage median / mean (ms) and the per-keyframe total's median, mean and sum (s)."""
    if not records:
        return "no keyframe processed"
    total = np.array([sum(r.values()) for r in records])
    lines = [
        f"keyframes {len(records)}: per keyframe median {np.median(total):.1f} ms, mean {total.mean():.1f} ms, "
        f"sum {total.sum() / 1e3:.1f} s (CPU time)"
    ]
    for stage in records[0]:
        values = np.array([r.get(stage, 0.0) for r in records])
        lines.append(f"  {stage:<22} median {np.median(values):8.1f}  mean {values.mean():8.1f}")
    return "\n".join(lines)


def main(argv: list[str]) -> None:
    if len(argv) < 3 or argv[1] != "--":
        raise SystemExit(__doc__)
    out = Path(argv[0])
    records: list[dict[str, float]] = []
    local_mapping.time = types.SimpleNamespace(perf_counter=time.thread_time)  # type: ignore[assignment]
    step = local_mapping.LocalMapper.step

    def timed_step(self: local_mapping.LocalMapper, kf: Any, abort: Any = None) -> Any:
        outcome = step(self, kf, abort)
        records.append(dict(outcome.timings_ms))
        return outcome

    local_mapping.LocalMapper.step = timed_step  # type: ignore[method-assign]

    def write() -> None:
        out.write_text(json.dumps(records))
        print(summarize(records))

    atexit.register(write)
    sys.argv = ["slamkit", *argv[2:]]
    slamkit_main()


if __name__ == "__main__":
    main(sys.argv[1:])
