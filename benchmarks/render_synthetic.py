"""Frames per second of the synthetic dataset at 640x480, per modality.

Usage: python benchmarks/render_synthetic.py [--scene room] [--frames 150] [--seed 0]

Each configuration is a SyntheticDataset; every 5th of the ``--frames`` first frames is rendered once first
(textures are generated on first sight and cached, and the compiled kernel is warmed up), then the
``--frames`` consecutive frames are timed through ``dataset[i]`` (everything a pipeline gets: images, noise,
depth, IMU). Two figures: frames per wall-clock second, and frames per CPU-second of this process (less
sensitive to other processes sharing the machine; OpenCV may use both cores, so it can be lower).
"""

from __future__ import annotations

import argparse
import time
from typing import Any

from slamkit.io.synthetic import SyntheticDataset

#: name -> dataset options of each measured modality.
MODALITIES: dict[str, dict[str, Any]] = {
    "grey": {"depth": False, "imu": False},
    "grey+depth": {"depth": True, "imu": False},
    "grey+depth+imu (default)": {},
    "grey+colour+depth": {"color": True},
    "stereo grey+depth": {"stereo": True},
    "grey+depth, no pixel noise": {"pixel_noise_std": 0.0},
}


def measure(scene: str, seed: int, n_frames: int, options: dict[str, Any]) -> tuple[float, float]:
    """(frames per wall-clock second, frames per process CPU-second) over ``n_frames`` consecutive frames."""
    ds = SyntheticDataset(scene=scene, seed=seed, **options)
    n = min(n_frames, len(ds))
    for i in range(0, n, 5):
        ds[i]
    wall, cpu = time.perf_counter(), time.process_time()
    for i in range(n):
        ds[i]
    return n / (time.perf_counter() - wall), n / (time.process_time() - cpu)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", default="room")
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(f"synthetic scene={args.scene} 640x480, {args.frames} frames per modality")
    print(f"{'modality':30s} {'frames/s':>9s} {'frames/CPU-s':>13s}")
    for name, options in MODALITIES.items():
        fps, fps_cpu = measure(args.scene, args.seed, args.frames, options)
        print(f"{name:30s} {fps:9.1f} {fps_cpu:13.1f}")


if __name__ == "__main__":
    main()
