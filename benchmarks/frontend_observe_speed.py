"""Per-call time of the front ends' ``observe`` on the room: monocular, stereo, RGB-D (issue 16's speed ratios).

Usage: python benchmarks/frontend_observe_speed.py [--frames 60] [--rounds 4] [--base /path/to/other/checkout]

Builds the three front ends of this checkout on the synthetic room (640 x 480, 1000 ORB features, each front end
with an extractor of its own) and, with ``--base``, the stereo and RGB-D front ends of another checkout's
slamkit/frontend/stereo.py and rgbd.py (loaded by path, so one process times both). The stereo front end is timed
three times: as configured (``parallel_matching`` off, the default), with ``parallel_matching`` on and with
``matching_pyramid=own`` (main's INTER_LINEAR matching pyramids, the base's records bit for bit). Every frame is observed by
every front end in turn, the order rotating frame to frame, so a change of machine load hits all alike; prints each
front end's median time (ms) and the median of its per-frame ratio to the monocular one (paired, less
load-sensitive than medians of separate runs). Checks first that the base's records and this checkout's with
``matching_pyramid=own`` are identical.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from slamkit.app import build_components
from slamkit.config import compose_config
from slamkit.frontend.mono import MonocularFrontEnd
from slamkit.frontend.rgbd import RgbdFrontEnd
from slamkit.frontend.stereo import StereoFrontEnd
from slamkit.plugins import ComponentRegistry


def _module(name: str, path: Path) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--base", type=Path, default=None, help="another checkout to compare with (its front ends)")
    args = parser.parse_args()
    registry = ComponentRegistry.discover()
    cfg = compose_config(["dataset.stereo=true", f"dataset.max_frames={args.frames + 5}"], registry=registry)
    components = build_components(cfg, registry)
    dataset = components["dataset"]
    camera = dataset.camera
    frames = [dataset[i] for i in range(5, args.frames + 5)]

    def extractor() -> Any:
        return build_components(cfg, registry)["features"]

    split = StereoFrontEnd(extractor(), parallel_matching=True)
    fronts: dict[str, Any] = {
        "mono": MonocularFrontEnd(extractor()),
        "stereo": StereoFrontEnd(extractor()),
        "stereo, parallel_matching on": split,
        "stereo, matching_pyramid own": StereoFrontEnd(extractor(), matching_pyramid="own"),
        "rgbd": RgbdFrontEnd(extractor()),
    }
    if args.base is not None:
        base_stereo = _module("base_stereo", args.base / "slamkit" / "frontend" / "stereo.py")
        base_rgbd = _module("base_rgbd", args.base / "slamkit" / "frontend" / "rgbd.py")
        fronts["stereo (base)"] = base_stereo.StereoFrontEnd(extractor())
        fronts["rgbd (base)"] = base_rgbd.RgbdFrontEnd(extractor())
    for name, front in fronts.items():
        if name.startswith("stereo"):
            front.bind_dataset(dataset)
        front.warm_up(camera)
        for data in frames[:3]:
            front.observe(data, camera)
    if args.base is not None:
        for data in frames[:10]:
            for ours, theirs in (("stereo, matching_pyramid own", "stereo (base)"), ("rgbd", "rgbd (base)")):
                a, b = fronts[ours].observe(data, camera), fronts[theirs].observe(data, camera)
                for field in ("u_right_px", "depth_m", "uv_px", "descriptors"):
                    if not np.array_equal(getattr(a, field), getattr(b, field), equal_nan=True):
                        raise SystemExit(f"{ours} and {theirs} differ in {field} at frame {data.index}")
        print("records identical to the base's (10 frames)")
    names = list(fronts)
    times: dict[str, list[float]] = {name: [] for name in names}
    for r in range(args.rounds):
        for j, data in enumerate(frames):
            k = (j + r) % len(names)
            for name in names[k:] + names[:k]:
                t0 = time.perf_counter()
                fronts[name].observe(data, camera)
                times[name].append(1e3 * (time.perf_counter() - t0))
    arr = {name: np.array(v) for name, v in times.items()}
    print(f"{args.frames} frames x {args.rounds} rounds, 1-minute load {os.getloadavg()[0]:.1f}, {os.cpu_count()} CPUs")
    for name, v in arr.items():
        ratio = float(np.median(v / arr["mono"]))
        print(f"  {name:30s} median {np.median(v):7.2f} ms   paired ratio to mono {ratio:.3f}")
    if args.base is not None:
        for ours in ("stereo", "stereo, parallel_matching on", "stereo, matching_pyramid own"):
            theirs = "stereo (base)"
            print(f"  paired {ours} / {theirs}: {float(np.median(arr[ours] / arr[theirs])):.3f}")
        print(f"  paired rgbd / rgbd (base): {float(np.median(arr['rgbd'] / arr['rgbd (base)'])):.3f}")


if __name__ == "__main__":
    main()
