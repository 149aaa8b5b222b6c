"""Time monocular initialisation's attempts (ORB-SLAM's Initializer) on recorded frames, extraction left out.

Usage: python benchmarks/init_attempt_speed.py [--frames 12] [--repeats 10] [--json F] [overrides ...]
       (default overrides: fr1_xyz monocular, seed 0; e.g. ``seed=0`` alone for the synthetic room)

Builds the sequential runner of ``slamkit run runner=sequential <overrides>``, extracts the first ``--frames`` frames
once with the initialisation extractor (the records depend on the image and the extractor only), then steps the
tracker through them ``--repeats`` times, each time from a reset tracker and a fresh ``default_rng(seed)`` (as a run
starts): every repeat makes the same attempts, and the same map, as the run's first frames. The tracker's front end
serves the recorded records, so each step's time is the attempt's work without the extraction (which real-time
playback could do ahead).

Prints, per frame: the median over repeats of the step's wall time (``track_ms``) and process CPU time (all
threads), of the matching (``MonocularInitialization.match``), of the Initializer (``initialize``) and of the map
creation (``create_initial_map``) on the frame that makes the map; and the attempt's message, with a digest of the
initial map's poses and points (to compare two trees: the same digest means the same initial map).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import statistics
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np

import slamkit.pipeline.tracking.tracker as tracker_module
from slamkit.app import build_runner
from slamkit.config import compose_config

FR1 = [
    "dataset=tum_rgbd",
    "dataset.root=/work/shared/datasets/tum_rgbd/rgbd_dataset_freiburg1_xyz",
    "dataset.use_depth=false",
    "seed=0",
]


class RecordedFrontEnd:
    """A front end that serves records extracted beforehand (by frame index); every other attribute is the wrapped
    front end's."""

    def __init__(self, frontend: Any, records: dict[int, Any]) -> None:
        self.frontend = frontend
        self.records = records

    def observe(self, data: Any, camera: Any, initializing: bool = False) -> Any:
        if initializing and data.index in self.records:
            return self.records[data.index]
        return self.frontend.observe(data, camera, initializing)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.frontend, name)


def _timed(fn: Callable[..., Any], out: dict[str, float], key: str) -> Callable[..., Any]:
    """fn wrapped to add its wall time (ms) to out[key]."""

    def wrapped(*args: Any, **kwargs: Any) -> Any:
        t0 = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            out[key] = out.get(key, 0.0) + (time.perf_counter() - t0) * 1e3

    return wrapped


def _map_digest(store: Any) -> str:
    """sha1 of the active map's keyframe poses and point positions (ids sorted)."""
    h = hashlib.sha1()
    for kf_id in sorted(store.keyframe_ids()):
        h.update(np.ascontiguousarray(store.get_keyframe(kf_id).T_c_w).tobytes())
    for pid in sorted(store.point_ids()):
        h.update(np.ascontiguousarray(store.get_point(pid).xyz_w).tobytes())
    return h.hexdigest()[:16]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=12, help="frames recorded (the attempts stop at the map)")
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--json", default=None, help="write the per-frame samples here")
    ap.add_argument("overrides", nargs="*", help="config overrides (default: fr1_xyz monocular, seed 0)")
    args = ap.parse_args()
    overrides = ["runner=sequential", "runner.progress=false", *(args.overrides or FR1)]
    cfg = compose_config(overrides)
    runner, dataset = build_runner(cfg)
    tracker: Any = runner.tracker
    camera = dataset.camera
    packets = []
    for data in dataset:
        packets.append(data)
        if len(packets) >= args.frames:
            break
    tracker.warm_up(camera)
    records = {d.index: tracker.frontend.observe(d, camera, True) for d in packets}
    tracker.frontend = RecordedFrontEnd(tracker.frontend, records)
    timings: dict[str, float] = {}
    init = tracker.init
    init.match = _timed(init.match, timings, "match_ms")
    init.initializer.initialize = _timed(init.initializer.initialize, timings, "initialize_ms")
    real_create = tracker_module.create_initial_map
    tracker_module.create_initial_map = _timed(real_create, timings, "create_map_ms")

    samples: dict[int, dict[str, list[float]]] = {}
    first: dict[int, dict[str, float]] = {}  # the first pass (after the tracker's warm-up), as a run's first attempts
    messages: dict[int, str] = {}
    digests = set()
    for rep in range(args.repeats + 1):  # the first pass warms up (compiled kernels' caches, thread pools)
        tracker.reset()
        rng = np.random.default_rng(int(cfg.seed))
        tracker.rng = rng
        init.rng = rng
        for data in packets:
            timings.clear()
            c0 = time.process_time()
            out = tracker.step(data, camera)
            cpu_ms = (time.process_time() - c0) * 1e3
            if rep == 0:
                first[data.index] = {**timings, "track_ms": out.timings_ms["track_ms"], "cpu_ms": cpu_ms}
            else:
                row = samples.setdefault(data.index, {})
                for key, value in {**timings, "track_ms": out.timings_ms["track_ms"], "cpu_ms": cpu_ms}.items():
                    row.setdefault(key, []).append(value)
                messages[data.index] = out.message
            if out.initialized_map:
                if rep > 0:
                    digests.add(_map_digest(tracker.store))
                break
    keys = ["track_ms", "cpu_ms", "match_ms", "initialize_ms", "create_map_ms"]
    print("frame " + " ".join(f"{k:>13}" for k in keys) + "  message")
    for index, row in samples.items():
        cells = [f"{statistics.median(row[k]):13.2f}" if k in row else f"{'':13}" for k in keys]
        print(f"{index:5d} " + " ".join(cells) + "  " + messages[index][:90])
    print("first pass (the run's own first attempts, after the tracker's warm-up):")
    for index, one in first.items():
        print(f"{index:5d} " + " ".join(f"{one[k]:13.2f}" if k in one else f"{'':13}" for k in keys))
    attempts = [statistics.median(r["track_ms"]) for r in samples.values() if "create_map_ms" not in r]
    attempts = attempts[1:]  # the first frame only becomes the reference
    if attempts:
        print(
            f"attempts (frames after the reference, before the map): median of per-frame medians "
            f"{statistics.median(attempts):.2f} ms track, max {max(attempts):.2f} ms"
        )
    print(f"initial map digest(s): {sorted(digests)}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(
                {"overrides": overrides, "samples": samples, "messages": messages, "digests": sorted(digests)},
                f,
                indent=1,
            )
    sys.stdout.flush()


if __name__ == "__main__":
    main()
