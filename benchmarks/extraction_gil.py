"""ORB extraction beside another busy thread: how much of its time is the GIL?

Usage: python benchmarks/extraction_gil.py [--frames 60] [--n-threads 2] [--switch-interval-ms 0.2]

Extracts 1000 ORB features from room frames (640x480) with the extractor slamkit runs, in the main thread,
while a second thread is
  - none:    absent;
  - python:  running Python code (holds the GIL, as local mapping's Python does in the threaded runner);
  - compiled: running a numba nogil loop (takes a core, not the GIL: a local BA's kernels);
  - both:    one of each.
Each call into OpenCV or a compiled kernel releases the GIL and, coming back while the Python thread runs,
waits up to the switch interval for it; extraction's time beside "python" against "none" measures how often
it does that. Prints the median per frame (ms) of each case, measured one after the other in this run.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import threading
import time

import numpy as np
from numba import njit
from slamkit_orb.orbslam_extractor import OrbSlamExtractor

from slamkit.io.synthetic import SyntheticDataset


@njit(nogil=True, cache=True)
def _spin(n: int) -> float:  # pragma: no cover - compiled
    s = 0.0
    for i in range(n):
        s += np.sqrt(i * 1.0)
    return s


def _python_busy(stop: threading.Event) -> None:
    while not stop.is_set():
        x = 0
        for i in range(1000):
            x += i


def _compiled_busy(stop: threading.Event) -> None:
    while not stop.is_set():
        _spin(2_000_000)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--n-threads", type=int, default=2, help="the extractor's level threads")
    parser.add_argument("--switch-interval-ms", type=float, default=0.2, help="as the threaded runner sets it")
    args = parser.parse_args()
    sys.setswitchinterval(args.switch_interval_ms / 1e3)
    dataset = SyntheticDataset(scene="room", depth=False, imu=False)
    images = [dataset[i].image for i in range(100, 100 + args.frames)]
    extractor = OrbSlamExtractor(n_features=1000, n_threads=args.n_threads)
    _spin(10)
    for image in images[:5]:
        extractor.extract(image)
    competitors = {
        "none": [],
        "python": [_python_busy],
        "compiled": [_compiled_busy],
        "both": [_python_busy, _compiled_busy],
    }
    for name, targets in competitors.items():
        stop = threading.Event()
        threads = [threading.Thread(target=t, args=(stop,), daemon=True) for t in targets]
        for thread in threads:
            thread.start()
        time.sleep(0.1)
        times = []
        for image in images:
            t0 = time.perf_counter()
            extractor.extract(image)
            times.append((time.perf_counter() - t0) * 1e3)
        stop.set()
        for thread in threads:
            thread.join()
        print(f"beside {name:9s} extraction median {statistics.median(times):6.1f} ms per frame")


if __name__ == "__main__":
    main()
