"""Extraction time and spatial coverage of ``features=orb`` (ORB-SLAM's extractor) vs ``features=opencv_orb``.

Usage: python benchmarks/orb_extractor.py [--frames 20] [--repeats 3] [--datasets ../shared/datasets]
                                          [--no-synthetic] [--json results.json]

Both extractors are built from their plugin config nodes (ORB-SLAM's parameters; 1000 features, 2000 on
KITTI as ORB-SLAM's KITTI settings) and run on the same images:
  - drawn: seeded cv2-drawn shapes, high contrast everywhere (640x480);
  - drawn-uneven: one strongly textured block, low-contrast texture elsewhere (640x480);
  - synthetic: frames of slamkit's SyntheticDataset, scene "room" (640x480);
  - tum/euroc/kitti: TUM RGB-D fr1/xyz (640x480), EuRoC V1_01_easy cam0 (752x480), KITTI 07 image_0
    (1226x370) from the shared datasets folder, when present.
Each frame is extracted once to warm up, then ``--repeats`` times per extractor, the two extractors
alternating so that both see the same machine load. Reported per source and extractor: median and 90th
percentile wall-clock ms per frame, CPU ms per frame of this process (all threads), mean number of
features, and coverage: the share of the cells of a 16 x 12 grid over the image (40 x 40 px at 640x480)
holding at least one feature, averaged over the frames.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from slamkit_orb.coverage import DEFAULT_GRID, grid_coverage
from slamkit_orb.patterns import textured_image, uneven_texture_image

from slamkit.plugins import ComponentRegistry

U8 = NDArray[np.uint8]
REPO_ROOT = Path(__file__).resolve().parents[1]
EXTRACTORS = ("orb", "opencv_orb")


@dataclass(frozen=True)
class Row:
    """One (source, extractor) line of the table."""

    source: str
    size: str
    n_frames: int
    n_features_budget: int
    extractor: str
    median_ms: float
    p90_ms: float
    cpu_ms: float
    mean_features: float
    mean_coverage: float


def _read(paths: list[Path]) -> Iterator[U8]:
    for path in paths:
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise FileNotFoundError(f"cannot read image {path}")
        yield np.asarray(image, np.uint8)


def _loader(files: list[Path]) -> Callable[[], list[U8]]:
    return lambda: list(_read(files))


def sources(n_frames: int, datasets: Path | None, synthetic: bool) -> list[tuple[str, int, Callable[[], list[U8]]]]:
    """(name, feature budget, loader of the frames) of every available source."""
    out: list[tuple[str, int, Callable[[], list[U8]]]] = [
        ("drawn", 1000, lambda: [textured_image(seed) for seed in range(n_frames)]),
        ("drawn-uneven", 1000, lambda: [uneven_texture_image(seed) for seed in range(n_frames)]),
    ]
    if synthetic:

        def synthetic_frames() -> list[U8]:
            from slamkit.io.synthetic import SyntheticDataset

            ds = SyntheticDataset(scene="room", depth=False, imu=False, max_frames=n_frames)
            return [ds[i].image for i in range(len(ds))]

        out.append(("synthetic", 1000, synthetic_frames))
    if datasets is not None:
        real = {
            "tum": (1000, datasets / "tum_rgbd" / "rgbd_dataset_freiburg1_xyz_first10" / "rgb"),
            "euroc": (1000, datasets / "euroc" / "V1_01_easy" / "mav0" / "cam0" / "data"),
            "kitti": (2000, datasets / "kitti" / "sequences" / "07" / "image_0"),
        }
        for name, (budget, folder) in real.items():
            files = sorted(folder.glob("*.png"))[:n_frames]
            if files:
                out.append((name, budget, _loader(files)))
    return out


def measure(
    name: str, budget: int, frames: list[U8], registry: ComponentRegistry, repeats: int, overrides: dict[str, Any]
) -> list[Row]:
    """Time both extractors on ``frames`` and measure their coverage."""
    extractors = {}
    for key in EXTRACTORS:
        node = {**registry.get("features", key).config_node(), "n_features": budget}
        if key == "orb":
            node.update(overrides)
        extractors[key] = registry.instantiate("features", node)
    wall: dict[str, list[float]] = {k: [] for k in EXTRACTORS}
    cpu = dict.fromkeys(EXTRACTORS, 0.0)
    count: dict[str, list[int]] = {k: [] for k in EXTRACTORS}
    coverage: dict[str, list[float]] = {k: [] for k in EXTRACTORS}
    for image in frames:
        h, w = image.shape
        for key, ex in extractors.items():
            features = ex.extract(image)  # warm-up (numba kernels, caches); also the coverage sample
            count[key].append(len(features))
            coverage[key].append(grid_coverage(features.uv_px, w, h, DEFAULT_GRID))
        for _ in range(repeats):
            for key, ex in extractors.items():
                c0, t0 = time.process_time(), time.perf_counter()
                ex.extract(image)
                wall[key].append(time.perf_counter() - t0)
                cpu[key] += time.process_time() - c0
    h, w = frames[0].shape
    return [
        Row(
            source=name,
            size=f"{w}x{h}",
            n_frames=len(frames),
            n_features_budget=budget,
            extractor=key,
            median_ms=1e3 * float(np.median(wall[key])),
            p90_ms=1e3 * float(np.percentile(wall[key], 90)),
            cpu_ms=1e3 * cpu[key] / len(wall[key]),
            mean_features=float(np.mean(count[key])),
            mean_coverage=float(np.mean(coverage[key])),
        )
        for key in EXTRACTORS
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=20, help="frames per source (default 20)")
    parser.add_argument("--repeats", type=int, default=3, help="timed extractions per frame and extractor")
    parser.add_argument("--datasets", type=Path, default=REPO_ROOT.parent / "shared" / "datasets")
    parser.add_argument("--no-synthetic", action="store_true", help="skip slamkit's SyntheticDataset frames")
    parser.add_argument("--threads", type=int, default=None, help="override features=orb's n_threads")
    parser.add_argument("--json", type=Path, default=None, help="also write the rows to this JSON file")
    args = parser.parse_args()
    if args.frames < 1 or args.repeats < 1:
        parser.error("--frames and --repeats must be >= 1")

    registry = ComponentRegistry.discover()
    overrides = {} if args.threads is None else {"n_threads": args.threads}
    datasets = args.datasets if args.datasets.is_dir() else None
    load = os.getloadavg()
    print(f"orb vs opencv_orb; coverage grid {DEFAULT_GRID[0]}x{DEFAULT_GRID[1]} cells; {os.cpu_count()} CPUs; ")
    print(f"load average before: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}; datasets: {datasets or 'absent'}")
    header = (
        f"{'source':13s} {'size':9s} {'N':>5s} {'extractor':11s} {'median ms':>9s} {'p90 ms':>7s} "
        f"{'CPU ms':>7s} {'features':>8s} {'coverage':>8s}"
    )
    print(header)
    print("-" * len(header))
    rows: list[Row] = []
    for name, budget, load_frames in sources(args.frames, datasets, not args.no_synthetic):
        frames = load_frames()
        for row in measure(name, budget, frames, registry, args.repeats, overrides):
            rows.append(row)
            print(
                f"{row.source:13s} {row.size:9s} {row.n_features_budget:5d} {row.extractor:11s} "
                f"{row.median_ms:9.2f} {row.p90_ms:7.2f} {row.cpu_ms:7.2f} {row.mean_features:8.1f} "
                f"{row.mean_coverage:8.3f}"
            )
    load = os.getloadavg()
    print(f"load average after: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    if args.json is not None:
        payload = {"grid": list(DEFAULT_GRID), "rows": [asdict(r) for r in rows]}
        args.json.write_text(json.dumps(payload, indent=2) + "\n")
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
