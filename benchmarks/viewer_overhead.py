"""What the rerun viewer costs tracking: `slamkit bench` runs of the same sequence without and with
``+viewer=rerun viewer.save=FILE.rrd``, interleaved (A B A B ...), on the same machine in the same minutes.

Usage: python benchmarks/viewer_overhead.py [--rounds 2] [--json OUT] [override ...]
       (default overrides: runner=threaded, the synthetic room, as fast as possible)

Prints the CPU model and load, then per round the tracking median (ms, per frame, waits for local mapping
included) and wall time of each side, and the ratio with/without of the medians over rounds. The acceptance of
issue 18: the tracking median with the viewer recording within 10% of without (ratio <= 1.10).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
from pathlib import Path
from typing import Any

from slamkit.bench.optimizer import machine_info
from slamkit.bench.run import bench_one


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("overrides", nargs="*", default=["runner=threaded"])
    args = parser.parse_args()
    machine = machine_info()
    print(f"machine: {machine}", flush=True)
    results: dict[str, list[dict[str, Any]]] = {"without": [], "with": []}
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.rounds):
            for side in ("without", "with"):
                extra = [] if side == "without" else ["+viewer=rerun", f"viewer.save={Path(tmp) / f'{i}.rrd'}"]
                load = os.getloadavg()[0]
                record = bench_one([*args.overrides, *extra], progress=False)
                if record["status"] != "ok":
                    raise SystemExit(f"{side} round {i}: {record.get('error')}")
                record["load_average_1min_before"] = load
                if side == "with":
                    record["rrd_mb"] = (Path(tmp) / f"{i}.rrd").stat().st_size / 1e6
                results[side].append(record)
                print(
                    f"round {i} {side:>7}: tracking median {record['tracking_ms_median']:.1f} ms, "
                    f"wall {record['wall_s']:.1f} s, keyframes {record['keyframes']}, load {load:.2f}"
                    + (f", {record['rrd_mb']:.0f} MB recorded" if side == "with" else ""),
                    flush=True,
                )
    med = {side: statistics.median(r["tracking_ms_median"] for r in rs) for side, rs in results.items()}
    ratio = med["with"] / med["without"]
    print(f"tracking median over rounds: without {med['without']:.1f} ms, with {med['with']:.1f} ms: {ratio:.2f}x")
    if args.json:
        args.json.write_text(
            json.dumps({"machine": machine, "ratio": ratio, "medians": med, "runs": results}, indent=1)
        )


if __name__ == "__main__":
    main()
