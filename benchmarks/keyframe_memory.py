"""Where a keyframe's memory goes (issue 15): tracemalloc between two frames of a sequential run.

Usage: python benchmarks/keyframe_memory.py A B [overrides...]   (e.g. ``150 600`` on the default synthetic room)

Runs ``slamkit run runner=sequential`` to frame B (``dataset.max_frames=B+1`` plus the overrides), starts tracemalloc
(one frame of traceback) at frame A and compares snapshots at A and B, both after a garbage collection. Prints the
keyframes in the map, keyframes inserted and map points at A and B, the traced memory grown per keyframe in the map
and per keyframe inserted, the 16 allocation sites (file:line) that grew most, per keyframe in the map, and the arrays
of one keyframe's observation record. A synthetic dataset renders its textures lazily: they show up as
``slamkit/io/synthetic/textures.py`` sites, the dataset's memory and not the map's.
"""

from __future__ import annotations

import gc
import sys
import tracemalloc
from typing import Any

import numpy as np

from slamkit.app import build_runner
from slamkit.config import compose_config


def main() -> None:
    a, b = int(sys.argv[1]), int(sys.argv[2])
    cfg = compose_config(["runner=sequential", "runner.progress=false", f"dataset.max_frames={b + 1}", *sys.argv[3:]])
    runner, ds = build_runner(cfg)
    notes: dict[int, tuple[tracemalloc.Snapshot, int, int, int, int]] = {}

    def count(what: str) -> int:
        atlas = runner.atlas
        return int(sum(getattr(atlas.get(m), what)() for m in atlas.map_ids()))

    def on_frame(out: Any) -> None:
        if out.frame_index not in (a, b):
            return
        gc.collect()
        if out.frame_index == a:
            tracemalloc.start(1)
        notes[out.frame_index] = (
            tracemalloc.take_snapshot(),
            count("n_keyframes"),
            len(runner.log.mapping),
            tracemalloc.get_traced_memory()[0],
            count("n_points"),
        )

    runner.run(ds, ds.camera, on_frame=on_frame)
    (sa, ka, ma, ta, pa), (sb, kb, mb, tb, pb) = notes[a], notes[b]
    dk = max(kb - ka, 1)
    print(
        f"frames {a}->{b}: keyframes in map {ka}->{kb}, inserted {ma}->{mb}, points {pa}->{pb}, traced "
        f"{ta / 2**20:.1f}->{tb / 2**20:.1f} MiB: {(tb - ta) / 2**10 / dk:.1f} KiB per keyframe in the map, "
        f"{(tb - ta) / 2**10 / max(mb - ma, 1):.1f} KiB per keyframe inserted"
    )
    keep = [tracemalloc.Filter(False, "*tracemalloc*")]
    for stat in sb.filter_traces(keep).compare_to(sa.filter_traces(keep), "lineno")[:16]:
        site = stat.traceback[0]
        print(f"{stat.size_diff / 2**10 / dk:8.1f} KiB/KF {stat.count_diff:8d} blocks  {site.filename}:{site.lineno}")
    store = runner.atlas.active
    kf = store.get_keyframe(store.keyframe_ids()[-1])
    arrays = {k: v.nbytes for k, v in vars(kf.features).items() if isinstance(v, np.ndarray)}
    print(f"one keyframe: {len(kf.features)} keypoints, arrays {arrays}, {sum(arrays.values())} bytes")
    print(f"points per keyframe in the map: {store.n_points() / max(store.n_keyframes(), 1):.1f}")


if __name__ == "__main__":
    main()
