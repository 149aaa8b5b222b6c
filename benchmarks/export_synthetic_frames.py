"""Write the synthetic world's grey frames to a folder of PNG files, to play them back like a recorded dataset.

Usage: python benchmarks/export_synthetic_frames.py OUT_DIR [--scene room] [--seed 0]

Real-time playback of the synthetic default renders every frame during the run (~6-9 ms of CPU on the same cores
as SLAM), which a camera would not cost. Played back from files (``dataset=folder``), each frame costs a PNG
decode (~3 ms, OpenCV, GIL released), as TUM or EuRoC frames do. The script prints the ``slamkit bench`` /
``slamkit run`` overrides that play the folder back with the scene's camera and frame rate. No ground truth goes
with the folder (ATE is not reported); run the synthetic dataset itself for accuracy.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
from tqdm import tqdm

from slamkit.io.synthetic import SyntheticDataset


def export(out_dir: Path, scene: str, seed: int) -> str:
    """Render every frame of ``scene`` into out_dir/NNNNNN.png; returns the dataset overrides to play it back."""
    dataset = SyntheticDataset(scene=scene, seed=seed, depth=False, imu=False)
    out_dir.mkdir(parents=True, exist_ok=True)
    for i in tqdm(range(len(dataset)), unit="frame", desc=f"rendering {scene}"):
        path = out_dir / f"{i:06d}.png"
        if not cv2.imwrite(str(path), dataset[i].image):
            raise OSError(f"could not write {path}")
    cam = dataset.camera
    fps = 1.0 / (dataset[1].timestamp_s - dataset[0].timestamp_s)
    camera = (
        f"{{model:pinhole,fx:{cam.fx},fy:{cam.fy},cx:{cam.cx},cy:{cam.cy},dist:[0,0,0,0,0],"
        f"width:{cam.width},height:{cam.height}}}"
    )
    return f"dataset=folder dataset.root={out_dir} dataset.fps={fps:g} '+dataset.camera={camera}'"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir", type=Path)
    parser.add_argument("--scene", default="room")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(export(args.out_dir, args.scene, args.seed))
    return 0


if __name__ == "__main__":
    sys.exit(main())
