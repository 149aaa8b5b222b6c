"""Map files (issue 17): save and load time, and peak memory against the map's size, for maps of 25 to 200 keyframes.

Usage: python benchmarks/map_save_load.py [--keyframes 25,50,100,200] [--features 1000] [--repeats 3]
       [--from FILE] [--json results.json]

The maps are built by hand with the shape of a real monocular map (ORB-SLAM's 1000 features per keyframe, as on
TUM fr1; ~35% of them observing a map point; each point seen by 2-6 keyframes; covisibility and spanning tree from
``update_connections``; bags of words from slamkit's built-in vocabulary), so the figures do not depend on how
many keyframes a sequence happens to make. ``--from FILE``: a map saved by a run (``slamkit run map.save=FILE``)
is timed too (loaded, then saved again and loaded back).

Per map: the file size; save time (``save_atlas``: read the maps under their read locks, write, checksum, fsync,
rename) and load time (``load_atlas``: read, checksum, parse, ``MapStore.restore``, keyframe database), the median
of ``--repeats`` (wall and process CPU time: on a loaded machine the CPU time is the cost); and the peak of memory allocated during a save and during a load (tracemalloc: numpy's buffers
included) divided by the file size (issue 17: memory while saving at most 2x the map's size).
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from slamkit_dbow.recognizer import DbowPlaceRecognizer

from slamkit.features import Features, Observations
from slamkit.geometry.camera import PinholeCamera
from slamkit.interfaces import MapStore
from slamkit.map.atlas import Atlas
from slamkit.map.entities import KeyFrame, MapPoint
from slamkit.map.ids import IdAllocator
from slamkit.map.mapfile import load_atlas, save_atlas
from slamkit.map.store import InMemoryMapStore

CAMERA = PinholeCamera(640, 480, 517.3, 516.5, 318.6, 255.3)  # TUM fr1's intrinsics


def new_store(ids: IdAllocator) -> MapStore:
    return InMemoryMapStore(ids=ids)


def build_map(n_keyframes: int, n_features: int, place: DbowPlaceRecognizer, seed: int = 0) -> Atlas:
    """A monocular-shaped map of ``n_keyframes`` keyframes (see the module docstring)."""
    rng = np.random.default_rng(seed)
    atlas = Atlas(new_store, place)
    store = atlas.active
    kf_ids: list[int] = []
    free: dict[int, int] = {}
    new_points_per_kf = int(0.35 * n_features / 4)  # each point seen by ~4 keyframes: ~35% of features tracked
    for i in range(n_keyframes):
        uv = rng.uniform([0, 0], [640, 480], (n_features, 2)).astype(np.float32)
        feats = Features(
            uv,
            uv,
            rng.integers(0, 8, n_features).astype(np.int32),
            rng.uniform(0, 360, n_features).astype(np.float32),
            rng.uniform(0, 100, n_features).astype(np.float32),
            rng.integers(0, 256, (n_features, 32), dtype=np.uint8),
            1.2,
            8,
        )
        obs = Observations.monocular(feats, CAMERA.unproject_image(uv.astype(np.float64)))
        kf_id = store.new_keyframe_id()
        T = np.eye(4)
        T[:3, 3] = [-0.02 * i, 0.0, 0.0]
        store.add_keyframe(KeyFrame(kf_id, 5 * i, i / 6.0, T, CAMERA, obs, np.full(n_features, -1, np.int64)))
        bow = place.transform(feats.descriptors)
        store.set_keyframe_bow(kf_id, bow)
        place.add(kf_id, bow)
        kf_ids.append(kf_id)
        free[kf_id] = 0
        if i == 0:
            continue
        for _ in range(new_points_per_kf if i > 1 else 2 * new_points_per_kf):
            observers = kf_ids[max(0, i - int(rng.integers(1, 6))) :]
            pid = store.new_point_id()
            store.add_point(
                MapPoint(
                    pid,
                    rng.uniform([-2, -2, 1], [2, 2, 4]),
                    rng.integers(0, 256, 32).astype(np.uint8),
                    observers[0],
                    observers[0],
                    rng.normal(size=3),
                    0.3,
                    5.0,
                )
            )
            for k in observers:
                if free[k] < n_features:
                    store.add_observation(pid, k, free[k])
                    free[k] += 1
        if i == 1:
            store.update_connections(kf_ids[0])
        store.update_connections(kf_id)
    return atlas


def measure(fn: Callable[[], Any]) -> tuple[float, int]:
    """(wall time s, peak bytes allocated above the start) of one call."""
    tracemalloc.start()
    tracemalloc.reset_peak()
    base = tracemalloc.get_traced_memory()[0]
    t0 = time.perf_counter()
    fn()
    wall = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1] - base
    tracemalloc.stop()
    return wall, peak


def bench_atlas(name: str, atlas: Atlas, repeats: int, directory: Path) -> dict[str, Any]:
    path = directory / f"{name}.slamkit"
    save_s, load_s, save_cpu, load_cpu = [], [], [], []
    save_peak = load_peak = 0
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        info = save_atlas(atlas, path)
        save_s.append(time.perf_counter() - t0)
        save_cpu.append(time.process_time() - c0)
        t0, c0 = time.perf_counter(), time.process_time()
        load_atlas(path, new_store, DbowPlaceRecognizer())
        load_s.append(time.perf_counter() - t0)
        load_cpu.append(time.process_time() - c0)
    _, save_peak = measure(lambda: save_atlas(atlas, path))
    _, load_peak = measure(lambda: load_atlas(path, new_store, DbowPlaceRecognizer()))
    size = info.size_bytes
    row = {
        "map": name,
        "keyframes": info.n_keyframes,
        "points": info.n_points,
        "size_mib": size / 2**20,
        "save_s": statistics.median(save_s),
        "load_s": statistics.median(load_s),
        "save_cpu_s": statistics.median(save_cpu),
        "load_cpu_s": statistics.median(load_cpu),
        "save_peak_x_size": save_peak / size,
        "load_peak_x_size": load_peak / size,
    }
    print(
        f"{name:>14} {row['keyframes']:>5} KF {row['points']:>7} pts {row['size_mib']:8.2f} MiB  save "
        f"{row['save_s']:6.3f} s (cpu {row['save_cpu_s']:.3f})  load {row['load_s']:6.3f} s (cpu {row['load_cpu_s']:.3f})  "
        f"peak save {row['save_peak_x_size']:.2f}x  "
        f"load {row['load_peak_x_size']:.2f}x",
        flush=True,
    )
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--keyframes", default="25,50,100,200", help="comma-separated map sizes (keyframes)")
    parser.add_argument("--features", type=int, default=1000, help="features per keyframe (ORB-SLAM TUM: 1000)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--from", dest="source", type=Path, default=None, help="a map file a run saved, timed too")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in (int(x) for x in args.keyframes.split(",") if x):
            place = DbowPlaceRecognizer()
            atlas = build_map(n, args.features, place)
            rows.append(bench_atlas(f"built-{n}", atlas, args.repeats, Path(tmp)))
        if args.source is not None:
            atlas = load_atlas(args.source, new_store, DbowPlaceRecognizer())
            rows.append(bench_atlas(args.source.stem, atlas, args.repeats, Path(tmp)))
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
