"""FAST-9/16 on whole ORB pyramids: OpenCV (detect + KeyPoint -> arrays) vs fast9.py's compiled detector.

Usage: nice -n 5 python benchmarks/fast9.py [--frames 5] [--repeats 20] [--source room|kitti]
                                            [--datasets ../shared/datasets]

On each frame's 8-level pyramid (scale 1.2, built as the extractor builds it: pyramid.py) it times, per frame:
  - fast opencv t=T:   cv2.FastFeatureDetector(T, nonmax) .detect on every level, then the conversion to
                       (N, 2) int32 / (N,) float32 arrays exactly as grid_fast.GridFast._fast does it;
  - fast compiled t=T: fast9.fast9_corners on every level (same arrays, checked equal once per frame);
  - grid <backend>:    GridFast.detect on every level as the extractor calls it ("auto" strategy, hints
                       from the previous frame): the extractor's whole FAST stage;
  - extract <backend> nT: OrbSlamExtractor(fast_backend=..., n_threads=T).extract (the whole extraction).
The variants are interleaved (each repeat runs all of them on the frame, in a rotating order) so that
machine load hits them alike; ratios are opencv / compiled medians from this one run.
"""

from __future__ import annotations

import argparse
import operator
import os
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray
from slamkit_orb.fast9 import fast9_corners
from slamkit_orb.grid_fast import FAST_BACKENDS, FastBackend, GridFast
from slamkit_orb.orbslam_extractor import OrbSlamExtractor
from slamkit_orb.pyramid import build_pyramid, level_sizes

U8 = NDArray[np.uint8]
REPO_ROOT = Path(__file__).resolve().parents[1]
_RESPONSE = operator.attrgetter("response")


def load_frames(source: str, n_frames: int, datasets: Path) -> list[U8]:
    """Grey frames: slamkit's synthetic room scene (640x480) or KITTI 07 image_0 (1241x376)."""
    if source == "room":
        from slamkit.io.synthetic import SyntheticDataset

        dataset = SyntheticDataset(scene="room", depth=False, imu=False, max_frames=n_frames)
        return [np.asarray(dataset[i].image, np.uint8) for i in range(len(dataset))]
    folder = datasets / "kitti" / "sequences" / "07" / "image_0"
    paths = sorted(folder.glob("*.png"))[:n_frames]
    if not paths:
        raise SystemExit(f"no KITTI frames under {folder}")
    return [np.asarray(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE), np.uint8) for p in paths]


def opencv_fast(
    levels: list[U8], detector: cv2.FastFeatureDetector
) -> list[tuple[NDArray[np.int32], NDArray[np.float32]]]:
    """OpenCV FAST on every level, converted to arrays as GridFast's opencv backend does."""
    out = []
    for level in levels:
        keypoints = detector.detect(level)
        xy = np.rint(cv2.KeyPoint.convert(keypoints)).astype(np.int32)
        response = np.fromiter(map(_RESPONSE, keypoints), dtype=np.float32, count=len(keypoints))
        out.append((xy, response))
    return out


def compiled_fast(levels: list[U8], threshold: int) -> list[tuple[NDArray[np.int32], NDArray[np.float32]]]:
    return [fast9_corners(level, threshold) for level in levels]


class GridStage:
    """GridFast over a pyramid with the extractor's "auto" strategy and per-level hints."""

    def __init__(self, backend: FastBackend) -> None:
        self.grid = GridFast(19, 30, 20, 7, backend)
        self.hints = np.ones(8)

    def __call__(self, levels: list[U8]) -> None:
        for i, level in enumerate(levels):
            self.hints[i] = self.grid.detect(level, "auto", float(self.hints[i])).weak_share


def _on_pyramid(pyramids: list[list[U8]], run: Callable[[list[U8]], object], i: int) -> object:
    return run(pyramids[i])


def _on_frame(frames: list[U8], extractor: OrbSlamExtractor, i: int) -> object:
    return extractor.extract(frames[i])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=5, help="frames (default 5)")
    parser.add_argument("--repeats", type=int, default=20, help="timed runs per frame and variant (default 20)")
    parser.add_argument("--source", choices=("room", "kitti"), default="room")
    parser.add_argument("--datasets", type=Path, default=REPO_ROOT.parent / "shared" / "datasets")
    args = parser.parse_args()
    if args.frames < 1 or args.repeats < 1:
        parser.error("--frames and --repeats must be >= 1")

    frames = load_frames(args.source, args.frames, args.datasets)
    h, w = frames[0].shape
    n_features = 2000 if args.source == "kitti" else 1000
    pyramids = [build_pyramid(f, level_sizes(w, h, 1.2, 8)) for f in frames]
    detectors = {t: cv2.FastFeatureDetector.create(t, True, cv2.FAST_FEATURE_DETECTOR_TYPE_9_16) for t in (20, 7)}
    extractors = {
        (backend, n): OrbSlamExtractor(n_features=n_features, n_threads=n, fast_backend=backend)
        for backend in FAST_BACKENDS
        for n in (1, 2)
    }
    grids = {backend: GridStage(backend) for backend in FAST_BACKENDS}

    corners: dict[int, list[int]] = {t: [] for t in (20, 7)}  # corners per frame over the pyramid
    for levels in pyramids:  # warm-up (numba compile or cache load) and the equality check
        for t, detector in detectors.items():
            ref, ours = opencv_fast(levels, detector), compiled_fast(levels, t)
            for (a, ra), (b, rb) in zip(ref, ours, strict=True):
                if not (np.array_equal(a, b) and np.array_equal(ra, rb)):
                    raise SystemExit(f"compiled FAST differs from OpenCV at threshold {t}")
            corners[t].append(sum(len(r) for r, _ in ref))
    for ex in extractors.values():
        ex.extract(frames[0])

    variants: dict[str, Callable[[int], object]] = {}
    for t, detector in detectors.items():
        variants[f"fast opencv t={t}"] = partial(_on_pyramid, pyramids, partial(opencv_fast, detector=detector))
        variants[f"fast compiled t={t}"] = partial(_on_pyramid, pyramids, partial(compiled_fast, threshold=t))
    for backend, stage in grids.items():
        variants[f"grid {backend}"] = partial(_on_pyramid, pyramids, stage)
    for (backend, n), ex in extractors.items():
        variants[f"extract {backend} {n}T"] = partial(_on_frame, frames, ex)

    names = list(variants)
    times: dict[str, list[float]] = {name: [] for name in names}
    load = os.getloadavg()
    print(
        f"source {args.source} {w}x{h}, {len(frames)} frames x {args.repeats} repeats, {os.cpu_count()} CPUs, "
        f"nice {os.nice(0)}, load average before {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}"
    )
    print(f"FAST corners per frame (8 levels): t=20 {np.mean(corners[20]):.0f}, t=7 {np.mean(corners[7]):.0f}")
    for r in range(args.repeats):
        for i in range(len(frames)):
            shift = (r * len(frames) + i) % len(names)  # rotate the order so no variant always runs first
            for name in names[shift:] + names[:shift]:
                t0 = time.perf_counter()
                variants[name](i)
                times[name].append(time.perf_counter() - t0)
    median = {name: 1e3 * float(np.median(v)) for name, v in times.items()}
    print(f"{'variant':24s} {'median ms/frame':>15s} {'p90 ms':>8s}")
    for name in names:
        print(f"{name:24s} {median[name]:15.3f} {1e3 * float(np.percentile(times[name], 90)):8.3f}")
    print("ratios opencv / compiled (medians of this run):")
    for t in (20, 7):
        print(f"  FAST t={t}: {median[f'fast opencv t={t}'] / median[f'fast compiled t={t}']:.2f}x")
    print(f"  grid FAST stage (20/7 with fallback): {median['grid opencv'] / median['grid compiled']:.2f}x")
    for n in (1, 2):
        print(f"  extract {n}T: {median[f'extract opencv {n}T'] / median[f'extract compiled {n}T']:.2f}x")
    load = os.getloadavg()
    print(f"load average after {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")


if __name__ == "__main__":
    main()
