"""Tracking time per frame of the monocular, stereo and RGB-D pipelines on the room, paired frame by frame
(issue 16's speed bars: stereo at most 1.6x, RGB-D at most 1.2x the monocular tracking median).

Usage: python benchmarks/tracking_speed_paired.py [--frames 300] [--seed 0] [--modes mono,stereo,rgbd] [--json F]
       [--base /path/to/other/checkout] [overrides for every run ...]; a mode may carry overrides of its own:
       ``--modes mono,stereo,stereo+features.n_threads=1``; with ``--base``, a mode ending in ``@base`` tracks with the
       other checkout's front end and ORB extractor (``--modes mono,stereo@base,stereo,rgbd@base,rgbd``: before and
       after in one run)

Builds one sequential runner per sensor (the commands' ``slamkit run runner=sequential seed=S dataset.max_frames=N
[frontend=stereo dataset.stereo=true | frontend=rgbd]``, each with its own dataset, extractor and map) and steps
them in turn, frame by frame, the order rotating each frame: frame k of every sensor is tracked within a fraction
of a second of the others, so a change of machine load (a shared machine) hits all alike. Each run is the same as
its ``slamkit run`` (the sequential runner is deterministic: the trajectories do not depend on the interleaving).

Prints, per sensor: the median tracking time (``timings_ms["track_ms"]``, the whole ``Tracker.step``: extraction
included; metrics.json's ``tracking_ms_median``), the median extraction time, the median process CPU time of the
step (all threads: robust to other processes' load, but blind to how well the step's threads overlap), and the
median of the per-frame ratio to the monocular step (paired). The CPU time is the tracker's step alone (the
runner's local mapping after a keyframe is not in it). Frames before the monocular map exists (its
two-view initialisation) are left out of every sensor's figures, as are frames a sensor did not track.
"""

from __future__ import annotations

import argparse
import importlib.util
import inspect
import json
import os
import sys
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from types import ModuleType
from typing import Any

import numba
import numpy as np

from slamkit.app import build_runner
from slamkit.config import compose_config

MODES: dict[str, list[str]] = {
    "mono": [],
    "stereo": ["frontend=stereo", "dataset.stereo=true"],
    "rgbd": ["frontend=rgbd"],
}


@numba.njit(nogil=True, cache=True)
def _spin(n: int) -> float:  # pragma: no cover - compiled
    """A compute-bound loop without memory traffic (the core check's work unit)."""
    x = 0.0
    for i in range(n):
        x += (i % 7) * 0.5
    return x


def core_scaling(n: int = 50_000_000) -> float:
    """How many times the work of two GIL-free threads goes faster than in one (2.0: two real cores free; near 1:
    the two vCPUs share one core, or another process holds one)."""
    _spin(1000)
    t0 = time.perf_counter()
    _spin(n)
    _spin(n)
    serial = time.perf_counter() - t0
    with ThreadPoolExecutor(2) as pool:
        t0 = time.perf_counter()
        list(pool.map(_spin, [n, n]))
        parallel = time.perf_counter() - t0
    return serial / parallel


def extraction_scaling(seed: int, pairs: int = 10, rounds: int = 3) -> tuple[float, float]:
    """How many times two ORB extractions in two threads (the stereo front end's schedule: each image alone in its
    thread, OpenCV's own threads off) go faster than the same two in series, on the room's first ``pairs`` stereo
    pairs, the two schedules alternating ``rounds`` times (best of each). Near 2: the two vCPUs run this image work
    (vectorised FAST, resizes, blurs) as two cores; near 1 while the spin check gives ~2: they share one core's
    vector units (hyperthreads the guest is not told about), and no schedule of the pair beats the work's sum."""
    import cv2

    cfg = compose_config(["frontend=stereo", "dataset.stereo=true", f"seed={seed}", f"dataset.max_frames={pairs}"])
    runner, dataset = build_runner(cfg)
    extractor: Any = getattr(runner.tracker.frontend, "extractor")  # noqa: B009 - FrontEnd does not declare it
    camera = dataset.camera
    images = [(d.image, d.image_right) for d in dataset]

    def one(image: Any) -> Any:
        return extractor.extract_with_pyramid(image, camera, threaded=False)

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    serial, parallel = np.inf, np.inf
    cpu_serial, cpu_parallel = 0.0, 0.0
    try:
        with ThreadPoolExecutor(1) as pool:
            for left, right in images[:2]:
                one(left), pool.submit(one, right).result()
            for _ in range(rounds):
                t0, c0 = time.perf_counter(), time.process_time()
                for left, right in images:
                    one(left)
                    one(right)
                serial = min(serial, time.perf_counter() - t0)
                cpu_serial += time.process_time() - c0
                t0, c0 = time.perf_counter(), time.process_time()
                for left, right in images:
                    future = pool.submit(one, right)
                    one(left)
                    future.result()
                parallel = min(parallel, time.perf_counter() - t0)
                cpu_parallel += time.process_time() - c0
    finally:
        cv2.setNumThreads(threads)
    return serial / parallel, cpu_parallel / cpu_serial


def _cpu_model() -> str:
    """The first "model name" of /proc/cpuinfo ("?" where there is none)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "?"


def _module(name: str, path: Path) -> ModuleType:
    """The Python file at ``path`` loaded as module ``name`` (its own imports resolve to this checkout's packages)."""
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise SystemExit(f"--base: cannot load {path}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def _kwargs(node: Any, cls: type) -> dict[str, Any]:
    """A config node's keys that ``cls.__init__`` takes (a key the other checkout does not know is left out)."""
    accepted = inspect.signature(cls).parameters
    return {str(k): v for k, v in node.items() if k != "_target_" and k in accepted}


def base_frontend(base: Path, cfg: Any, dataset: Any) -> Any:
    """The front end of ``cfg`` built from the other checkout's front-end module and slamkit_orb extractor, each
    loaded by path (the helpers they import, e.g. the level kernels, are this checkout's)."""
    orb = _module("base_orbslam_extractor", base / "plugins" / "slamkit_orb" / "orbslam_extractor.py")
    target = str(cfg.frontend._target_)
    module_name, class_name = target.rsplit(".", 1)
    front_module = _module("base_" + module_name.replace(".", "_"), base / (module_name.replace(".", "/") + ".py"))
    features = {str(k): v for k, v in cfg.features.items() if k != "_target_"}
    extractor = orb.OrbSlamExtractor(**features)
    factor = float(cfg.pipeline.tracking.init_feature_factor)
    init = None
    if factor != 1:
        init = orb.OrbSlamExtractor(**{**features, "n_features": round(int(features["n_features"]) * factor)})
    cls = getattr(front_module, class_name)
    front = cls(extractor, init, **_kwargs(cfg.frontend, cls))
    if hasattr(front, "bind_dataset"):
        front.bind_dataset(dataset)
    return front


def _cpu_timed(step: Callable[..., Any], out: list[float]) -> Callable[..., Any]:
    """``step`` that appends its process CPU time (ms, all threads) to ``out``."""

    def timed(*args: Any, **kwargs: Any) -> Any:
        c0 = time.process_time()
        try:
            return step(*args, **kwargs)
        finally:
            out.append((time.process_time() - c0) * 1e3)

    return timed


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--modes", default="mono,stereo,rgbd")
    parser.add_argument("--json", type=Path, default=None, help="write the per-frame timings here")
    parser.add_argument("overrides", nargs="*", help="config overrides given to every run")
    parser.add_argument(
        "--core-check",
        action="store_true",
        help="first time two compute-bound threads against one, and two ORB extractions in two threads against in series",
    )
    parser.add_argument("--base", type=Path, default=None, help="another checkout, for the modes ending in @base")
    args = parser.parse_args()
    print(f"CPU: {_cpu_model()}, {os.cpu_count()} logical CPUs; 1-minute load {os.getloadavg()[0]:.1f}")
    if args.core_check:
        print(f"two threads against one: {core_scaling():.2f}x faster (2.00: two free cores)")
        speedup, cpu_inflation = extraction_scaling(args.seed)
        print(
            f"two ORB extractions in two threads against in series: {speedup:.2f}x faster, {cpu_inflation:.2f}x the CPU "
            "time (the stereo pair's schedule; near 1.0x faster and well above 1.0x the CPU with the line above near "
            "2.0: the two threads slow each other down, e.g. hyperthreads of one core)"
        )
    modes = args.modes.split(",")
    if "mono" not in modes:
        raise SystemExit("--modes must include mono (the ratios' reference)")
    runs: dict[str, Any] = {}
    cpu_ms: dict[str, list[float]] = {}  # the process CPU time of each Tracker.step (local mapping not included)
    for mode in modes:
        spec, _, tree = mode.partition("@")
        if tree and (tree != "base" or args.base is None):
            raise SystemExit(f"mode {mode}: only @base, with --base")
        cfg = compose_config(
            ["runner=sequential", "runner.progress=false", f"seed={args.seed}", f"dataset.max_frames={args.frames}"]
            + MODES[spec.split("+")[0]]
            + spec.split("+")[1:]
            + list(args.overrides)
        )
        runner, dataset = build_runner(cfg)
        if tree:
            runner.tracker.frontend = base_frontend(args.base, cfg, dataset)
        runner.begin(dataset, dataset.camera)
        runner.tracker.step = _cpu_timed(runner.tracker.step, cpu_ms.setdefault(mode, []))  # type: ignore[method-assign]
        runs[mode] = (runner, dataset, iter(dataset))
    # per mode, per frame: (state ok, track_ms wall, extract_ms wall, step cpu ms)
    rows: dict[str, list[tuple[bool, float, float, float]]] = {m: [] for m in modes}
    load = [os.getloadavg()[0]]
    for k in range(args.frames):
        order = modes[k % len(modes) :] + modes[: k % len(modes)]
        for mode in order:
            runner, dataset, frames = runs[mode]
            data = next(frames)
            out = runner.step(data, dataset.camera)
            cpu = cpu_ms[mode].pop()
            rows[mode].append(
                (
                    out.state.value == "ok",
                    out.timings_ms.get("track_ms", np.nan),
                    out.timings_ms.get("extract_ms", np.nan),
                    cpu,
                )
            )
        if k % 50 == 0:
            load.append(os.getloadavg()[0])
    for runner, _, _ in runs.values():
        runner.end()
    load.append(os.getloadavg()[0])
    mono_init = next((i for i, r in enumerate(rows["mono"]) if r[0]), 0)
    use = np.zeros(args.frames, bool)
    use[mono_init + 1 :] = True
    for mode in modes:
        use &= np.array([r[0] for r in rows[mode]])
    print(
        f"frames used: {int(use.sum())} of {args.frames} (mono initialised at {mono_init}); 1-minute load {min(load):.1f}-{max(load):.1f}"
    )
    mono = np.array([r[1] for r in rows["mono"]])
    mono_cpu = np.array([r[3] for r in rows["mono"]])
    print(
        f"{'sensor':14s} {'track ms':>9s} {'extract':>8s} {'cpu ms':>8s} {'ratio of medians':>17s} {'paired ratio':>13s} {'cpu ratio':>10s}"
    )
    for mode in modes:
        t = np.array([r[1] for r in rows[mode]])
        e = np.array([r[2] for r in rows[mode]])
        c = np.array([r[3] for r in rows[mode]])
        print(
            f"{mode:14s} {np.median(t[use]):9.2f} {np.median(e[use]):8.2f} {np.median(c[use]):8.2f} "
            f"{np.median(t[use]) / np.median(mono[use]):17.3f} {np.median(t[use] / mono[use]):13.3f} "
            f"{np.median(c[use]) / np.median(mono_cpu[use]):10.3f}"
        )
    if args.json is not None:
        args.json.write_text(json.dumps({"load": load, "rows": rows, "frames_used": use.tolist()}))


if __name__ == "__main__":
    main()
