"""ORB-SLAM3 and slamkit, monocular, on the same sequence, back to back, on the same machine.

Usage::

    python benchmarks/orbslam3_side_by_side.py tum  ../shared/datasets/tum_rgbd/rgbd_dataset_freiburg1_xyz \\
        --peers ../peers --runs 3 --out side_by_side/fr1_xyz
    python benchmarks/orbslam3_side_by_side.py kitti ../shared/datasets/kitti --sequence 07 \\
        --peers ../peers --runs 3 --out side_by_side/kitti07 -- +experiment=kitti07

``--stride N`` (TUM) gives both systems every Nth frame of the sequence (a folder ``OUT/strideN/<name>`` whose
rgb.txt lists lines 0, N, 2N, ... and links the rest): N times the motion between frames, for a robustness figure
on the same footage.

ORB-SLAM3 is the C++ inside the PyPI wheel ``pyorbslam3`` (GPL-3.0), run by the peers' runner
``run_pyorbslam3.py`` with the Python of a virtual environment that has the wheel (``--peers DIR`` holds the
runner, ``configs/`` with ORB-SLAM3 settings files and ``vocab/ORBvoc_local.txt``; ``--venv`` defaults to
``DIR/venv_pos``; the set-up is in the peers' README.md). Without the runner, the venv or the wheel the script
prints why and exits 0 (it is optional: nothing of slamkit depends on it).

For run i = 1..N it runs ORB-SLAM3 once, then ``slamkit run`` with seed ``seeds[i]`` (the current Python's
slamkit, ``runner=sequential`` unless ``--runner``), so both systems share the machine's load of the same minutes.
Figures per run, both systems measured the same way:

- init frame: 0-based index of the first frame with a pose (ORB-SLAM3: the first ``pose_valid`` frame of
  ``traj_online.txt``; slamkit: the first ``ok`` row of ``frames.csv``);
- tracked: % of the frames from the init frame on that have a pose;
- ATE all / KF: RMSE (m, printed in cm) of the final frame trajectory / keyframe trajectory after Sim3 Umeyama
  alignment (``slamkit.eval.metrics.compute_ate``, the ``slamkit eval --align sim3`` code; ORB-SLAM3's
  ``SaveTrajectoryEuRoC`` / ``SaveKeyFrameTrajectoryTUM``, slamkit's trajectory.tum / keyframes.tum);
- fps: frames / wall time of the frame loop (ORB-SLAM3: its ``fps_loop``, frames fed as fast as tracking takes
  them, local mapping in its own thread; slamkit: frames / ``wall_s``: with the sequential runner local mapping
  and loop closing run in line, so slamkit's fps is a lower bound of its threaded runner's);
- track ms: median per-frame tracking time.

It prints the CPU model, the core count and the 1-minute load average before and after every run, the median of
each figure per system and the ratio slamkit / ORB-SLAM3 of the medians, and writes everything to
``OUT/side_by_side.json`` (raw outputs under ``OUT/orbslam3_runI`` and ``OUT/slamkit_seedS``). ORB-SLAM3 is not
deterministic (threads, RANSAC): quote medians of at least 3 runs.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import statistics
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

#: ORB-SLAM3's monocular settings file for each dataset (ORB-SLAM3 Examples/Monocular), in PEERS/configs.
KITTI_SETTINGS = {
    **{f"{i:02d}": "mono_KITTI00-02.yaml" for i in range(3)},
    **{f"{i:02d}": "mono_KITTI04-12.yaml" for i in range(4, 13)},
}
SETTINGS = {"tum": "mono_TUM1.yaml", "euroc": "mono_EuRoC.yaml"}


@dataclass
class RunFigures:
    """One run of one system. ATE in metres, fps in frames per second, track_ms median per frame."""

    system: str
    run: str
    out_dir: str
    frames: int
    init_frame: int | None
    tracked_pct: float | None
    ate_all_m: float | None
    ate_all_poses: int
    ate_kf_m: float | None
    ate_kf_poses: int
    fps: float | None
    track_ms: float | None
    wall_s: float
    load_before: float
    load_after: float
    error: str = ""


@dataclass(frozen=True)
class Sequence:
    """Where a sequence's images and ground truth are, for both systems.

    orb_seq / orb_fmt: what run_pyorbslam3.py takes (--seq, --fmt); timestamps_s: (N,) s of the frames both
    systems read, in order; gt / gt_times: ground-truth file and, for KITTI poses, its times.txt.
    """

    name: str
    orb_seq: Path
    orb_fmt: str
    timestamps_s: list[float]
    gt: Path
    gt_times: Path | None
    slamkit_overrides: tuple[str, ...]
    settings_name: str


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``, as `slamkit bench` reads it) and the cores this process may use."""
    from slamkit.bench.optimizer import machine_info

    model = machine_info()["cpu"]
    n = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return f"{model}, {n} cores"


def load1() -> float:
    """1-minute load average (NaN where the platform has none)."""
    try:
        return os.getloadavg()[0]
    except OSError:
        return float("nan")


def tum_timestamps(seq: Path) -> list[float]:
    """Colour-frame timestamps (s) of a TUM RGB-D sequence's rgb.txt, in file order."""
    out = []
    for line in (seq / "rgb.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            out.append(float(line.split()[0]))
    return out


def strided_tum_sequence(seq: Path, stride: int, out: Path) -> Path:
    """A TUM sequence folder under ``out`` holding every ``stride``-th colour frame of ``seq`` (its rgb.txt lines 0,
    stride, 2 stride, ... in file order; the images, depth and ground truth linked, not copied): the same scene with
    ``stride`` times the motion between frames, for both systems. Named as ``seq`` (the TUM reader takes the camera
    from the folder name); returns its path."""
    folder = out / f"stride{stride}" / seq.name
    folder.mkdir(parents=True, exist_ok=True)
    lines = (seq / "rgb.txt").read_text().splitlines()
    comments = [line for line in lines if line.startswith("#")]
    frames = [line for line in lines if line.strip() and not line.startswith("#")]
    header = f"# every {stride}th frame of {seq / 'rgb.txt'} (orbslam3_side_by_side.py --stride {stride})"
    (folder / "rgb.txt").write_text("\n".join([*comments, header, *frames[::stride]]) + "\n")
    for entry in seq.iterdir():
        link = folder / entry.name
        if entry.name != "rgb.txt" and not link.exists():
            link.symlink_to(entry.resolve())
    return folder


def make_sequence(args: argparse.Namespace) -> Sequence:
    """The sequence described by the command line (dataset kind, path, KITTI sequence, --gt)."""
    path: Path = args.path.resolve()
    if args.kind == "tum":
        gt = (args.gt or path / "groundtruth.txt").resolve()
        if args.stride > 1:
            path = strided_tum_sequence(path, args.stride, args.out.resolve())
        ts = tum_timestamps(path)
        name = path.name if args.stride == 1 else f"{path.name}, every {args.stride}th frame"
        return Sequence(name, path, "tum", ts, gt, None, ("dataset=tum_rgbd", f"dataset.root={path}"), SETTINGS["tum"])
    if args.kind == "kitti":
        seq = path / "sequences" / args.sequence
        times = [float(x) for x in (seq / "times.txt").read_text().split()]
        # The peers' runner (like slamkit's reader) uses the frames whose image exists.
        ts = [t for i, t in enumerate(times) if (seq / "image_0" / f"{i:06d}.png").is_file()]
        overrides = ("dataset=kitti", f"dataset.root={path}", f"dataset.sequence={args.sequence}")
        gt = args.gt or path / "poses" / f"{args.sequence}.txt"
        gt_times = None if args.gt else seq / "times.txt"
        return Sequence(
            f"kitti_{args.sequence}", seq, "kitti", ts, gt, gt_times, overrides, KITTI_SETTINGS[args.sequence]
        )
    if args.gt is None:
        raise SystemExit(
            "euroc: give --gt FILE, the cam0 ground truth as a TUM file (EuRoC's data.csv is the body pose)"
        )
    lines = (path / "mav0" / "cam0" / "data.csv").read_text().splitlines()
    ts = [int(line.split(",")[0]) * 1e-9 for line in lines if line.strip() and not line.startswith("#")]
    return Sequence(
        path.name, path, "euroc", ts, args.gt, None, ("dataset=euroc", f"dataset.root={path}"), SETTINGS["euroc"]
    )


def ate(seq: Sequence, estimate: Path) -> tuple[float | None, int, str]:
    """Sim3-aligned ATE RMSE (m) and matched poses of a TUM trajectory file; (None, 0, why) when it fails."""
    from slamkit.errors import SlamkitError
    from slamkit.eval.metrics import compute_ate
    from slamkit.io.trajectory_io import read_trajectory

    if not estimate.is_file() or estimate.stat().st_size == 0:
        return None, 0, f"{estimate.name}: no trajectory"
    try:
        gt = read_trajectory(seq.gt, "auto", times_path=seq.gt_times)
        est = read_trajectory(estimate, "tum")
        res = compute_ate(gt, est, "sim3", 0.01)
    except (SlamkitError, OSError, ValueError) as exc:
        return None, 0, f"{estimate.name}: {exc}"
    return res.rmse_m, res.matched_poses, ""


def frame_index(seq: Sequence, t_s: float) -> int:
    """0-based index of the frame whose timestamp is nearest ``t_s``."""
    return int(np.argmin(np.abs(np.asarray(seq.timestamps_s) - t_s)))


def run_orbslam3(args: argparse.Namespace, seq: Sequence, i: int, out: Path) -> RunFigures:
    """One ORB-SLAM3 run through the peers' runner; figures from its outputs."""
    settings = args.settings or args.peers / "configs" / seq.settings_name
    cmd = [str(args.venv / "bin" / "python"), str(args.peers / "run_pyorbslam3.py"), "--seq", str(seq.orb_seq)]
    cmd += ["--fmt", seq.orb_fmt, "--settings", str(settings), "--vocab", str(args.vocab), "--out", str(out)]
    if args.max_frames:
        cmd += ["--max-frames", str(args.max_frames)]
    n = len(seq.timestamps_s) if not args.max_frames else min(args.max_frames, len(seq.timestamps_s))
    out.mkdir(parents=True, exist_ok=True)
    lb, t0 = load1(), time.perf_counter()
    with open(out / "run.log", "w") as log:
        proc = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, timeout=args.timeout, check=False)
    wall, la = time.perf_counter() - t0, load1()
    fig = RunFigures("ORB-SLAM3", f"run{i}", str(out), n, None, None, None, 0, None, 0, None, None, wall, lb, la)
    if proc.returncode != 0 or not (out / "stats.json").is_file():
        fig.error = f"exit {proc.returncode}, see {out / 'run.log'}"
        return fig
    return read_orbslam3_figures(fig, seq, out)


def read_orbslam3_figures(fig: RunFigures, seq: Sequence, out: Path) -> RunFigures:
    """Fill ``fig`` (``fig.frames`` = frames fed) from the peers' runner's outputs in ``out``: stats.json,
    traj_online.txt (one line per frame with a pose, online), traj.txt and kf_traj.txt (final, TUM)."""
    stats = json.loads((out / "stats.json").read_text())
    fig.fps, fig.track_ms = stats.get("fps_loop"), stats.get("track_ms_median")
    online_path = out / "traj_online.txt"
    lines = online_path.read_text().splitlines() if online_path.is_file() else []
    online = sorted({frame_index(seq, float(line.split()[0])) for line in lines if line.strip()})
    if online:
        fig.init_frame = online[0]
        fig.tracked_pct = 100.0 * len(online) / max(fig.frames - fig.init_frame, 1)
    fig.ate_all_m, fig.ate_all_poses, e1 = ate(seq, out / "traj.txt")
    fig.ate_kf_m, fig.ate_kf_poses, e2 = ate(seq, out / "kf_traj.txt")
    fig.error = "; ".join(e for e in (e1, e2) if e)
    return fig


def run_slamkit(args: argparse.Namespace, seq: Sequence, seed: int, out: Path) -> RunFigures:
    """One ``slamkit run`` (this Python's slamkit) with ``seed``; figures from its run directory."""
    cmd = [sys.executable, "-m", "slamkit", "run", f"hydra.run.dir={out}", f"seed={seed}", f"runner={args.runner}"]
    cmd += ["runner.progress=false", *seq.slamkit_overrides]
    if args.max_frames:
        cmd.append(f"dataset.max_frames={args.max_frames}")
    cmd += args.overrides
    out.mkdir(parents=True, exist_ok=True)
    lb, t0 = load1(), time.perf_counter()
    with open(out / "run.log", "w") as log:
        log.write(" ".join(cmd) + "\n")
        log.flush()
        proc = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, timeout=args.timeout, check=False)
    wall, la = time.perf_counter() - t0, load1()
    fig = RunFigures("slamkit", f"seed{seed}", str(out), 0, None, None, None, 0, None, 0, None, None, wall, lb, la)
    if proc.returncode != 0 or not (out / "frames.csv").is_file():
        fig.error = f"exit {proc.returncode}, see {out / 'run.log'}"
        return fig
    return read_slamkit_figures(fig, seq, out)


def read_slamkit_figures(fig: RunFigures, seq: Sequence, out: Path) -> RunFigures:
    """Fill ``fig`` from a slamkit run directory: frames.csv (one row per frame, state ``ok`` = a pose),
    metrics.json (wall_s, tracking_ms_median), trajectory.tum and keyframes.tum."""
    with open(out / "frames.csv") as f:
        rows = list(csv.DictReader(f))
    fig.frames = len(rows)
    init = next((int(r["frame"]) for r in rows if r["state"] == "ok"), None)
    if init is not None:
        fig.init_frame = init
        after = [r for r in rows if int(r["frame"]) >= init]
        fig.tracked_pct = 100.0 * sum(r["state"] == "ok" for r in after) / len(after)
    metrics = json.loads((out / "metrics.json").read_text()) if (out / "metrics.json").is_file() else {}
    if metrics.get("wall_s"):
        fig.fps = fig.frames / float(metrics["wall_s"])
    fig.track_ms = metrics.get("tracking_ms_median")
    fig.ate_all_m, fig.ate_all_poses, e1 = ate(seq, out / "trajectory.tum")
    fig.ate_kf_m, fig.ate_kf_poses, e2 = ate(seq, out / "keyframes.tum")
    fig.error = "; ".join(e for e in (e1, e2) if e)
    return fig


#: (attribute, column title, format) of the table's columns; ATE columns are printed in cm.
FIELDS: tuple[tuple[str, str, str], ...] = (
    ("init_frame", "init", "{:.0f}"),
    ("tracked_pct", "tracked %", "{:.1f}"),
    ("ate_all_m", "ATE all cm", "{:.2f}"),
    ("ate_kf_m", "ATE KF cm", "{:.2f}"),
    ("fps", "fps", "{:.1f}"),
    ("track_ms", "track ms", "{:.1f}"),
)


def cell(fig: RunFigures | dict[str, float | None], key: str, fmt: str) -> str:
    v = fig[key] if isinstance(fig, dict) else getattr(fig, key)
    if v is None:
        return "-"
    return fmt.format(100.0 * v if key.startswith("ate") else v)


def medians(figs: list[RunFigures]) -> dict[str, float | None]:
    """Median of each figure over the runs that have it (None when no run has it)."""
    out: dict[str, float | None] = {}
    for key, _, _ in FIELDS:
        vals = [getattr(f, key) for f in figs if getattr(f, key) is not None]
        out[key] = float(statistics.median(vals)) if vals else None
    return out


def row(f: RunFigures) -> str:
    """One run's line of the table (load: 1-minute load average before > after the run)."""
    vals = "".join(f"{cell(f, k, fmt):>11}" for k, _, fmt in FIELDS)
    return f"{f.system:<10} {f.run:<7}{vals}{f.load_before:>6.1f}>{f.load_after:<5.1f}  {f.error}"


def table(seq: Sequence, figs: list[RunFigures], env: dict[str, Any]) -> str:
    head = f"{'system':<10} {'run':<7}" + "".join(f"{h:>11}" for _, h, _ in FIELDS) + f"{'load':>12}  note"
    lines = [f"{seq.name}: {len(seq.timestamps_s)} frames; CPU {env['cpu']}; {env['date_utc']}", head]
    lines += [row(f) for f in figs]
    med = {s: medians([f for f in figs if f.system == s]) for s in ("ORB-SLAM3", "slamkit")}
    for s, m in med.items():
        lines.append(f"{s:<10} {'median':<7}" + "".join(f"{cell(m, k, fmt):>11}" for k, _, fmt in FIELDS))
    ratio = []
    for key, _, _ in FIELDS:
        a, b = med["slamkit"][key], med["ORB-SLAM3"][key]
        ratio.append("-" if a is None or not b else f"{a / b:.2f}")
    lines.append(f"{'slamkit / ORB-SLAM3':<18}" + "".join(f"{r:>11}" for r in ratio))
    return "\n".join(lines)


def skip_reason(args: argparse.Namespace) -> str:
    """Why ORB-SLAM3 cannot run here ('' when it can)."""
    if args.peers is None:
        return "no --peers DIR (or SLAMKIT_PEERS) holding run_pyorbslam3.py"
    if not (args.peers / "run_pyorbslam3.py").is_file():
        return f"{args.peers}/run_pyorbslam3.py not found"
    py = args.venv / "bin" / "python"
    if not py.is_file():
        return f"no virtual environment at {args.venv} (see the peers' README.md for the set-up)"
    probe = subprocess.run([str(py), "-c", "import pyorbslam3"], capture_output=True, text=True, check=False)
    if probe.returncode != 0:
        return f"pyorbslam3 is not installed in {args.venv}: {probe.stderr.strip().splitlines()[-1:]}"
    if not Path(args.vocab).is_file():
        return f"no ORB vocabulary at {args.vocab} (train one: the peers' train_orbvoc.py or `slamkit vocab train`)"
    return ""


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("kind", choices=("tum", "kitti", "euroc"), help="dataset format")
    p.add_argument("path", type=Path, help="TUM/EuRoC sequence folder, or the KITTI root (sequences/, poses/)")
    p.add_argument("--sequence", default="07", help="KITTI sequence (default 07)")
    p.add_argument("--gt", type=Path, default=None, help="ground truth (TUM file); needed for EuRoC (cam0 poses)")
    env_peers = os.environ.get("SLAMKIT_PEERS")
    p.add_argument("--peers", type=Path, default=Path(env_peers) if env_peers else None, help="peers folder")
    p.add_argument("--venv", type=Path, default=None, help="venv with pyorbslam3 (default PEERS/venv_pos)")
    p.add_argument("--vocab", type=Path, default=None, help="ORB vocabulary (default PEERS/vocab/ORBvoc_local.txt)")
    p.add_argument("--settings", type=Path, default=None, help="ORB-SLAM3 settings (default PEERS/configs/mono_*.yaml)")
    p.add_argument("--runs", type=int, default=3, help="runs of each system (default 3)")
    p.add_argument(
        "--seeds",
        default=None,
        help="slamkit seeds, comma-separated (default 0..runs-1; fewer: slamkit in the first runs)",
    )
    p.add_argument("--resume", action="store_true", help="read the runs already complete in OUT instead of rerunning")
    p.add_argument("--runner", default="sequential", help="slamkit runner (default sequential: deterministic)")
    p.add_argument("--max-frames", type=int, default=0, help="stop both after this many frames (0: all)")
    p.add_argument(
        "--stride",
        type=int,
        default=1,
        help="TUM only: both systems read every STRIDE-th frame (STRIDE times the motion between frames; default 1)",
    )
    p.add_argument("--only", choices=("both", "orbslam3", "slamkit"), default="both")
    p.add_argument("--timeout", type=float, default=3600.0, help="seconds per run")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    argv = list(sys.argv[1:] if argv is None else argv)
    # Everything after "--" is for slamkit (argparse cannot take a positional list after the options).
    overrides = argv[argv.index("--") + 1 :] if "--" in argv else []
    args = p.parse_args(argv[: argv.index("--")] if "--" in argv else argv)
    args.overrides = overrides
    if args.peers is not None:
        args.peers = args.peers.resolve()
        args.venv = (args.venv or args.peers / "venv_pos").resolve()
        args.vocab = (args.vocab or args.peers / "vocab" / "ORBvoc_local.txt").resolve()
    seeds = [int(s) for s in args.seeds.split(",")] if args.seeds else list(range(args.runs))
    if len(seeds) > args.runs:
        p.error(f"--seeds gives {len(seeds)} seeds for --runs {args.runs}")
    args.seed_list = seeds
    if args.stride < 1:
        p.error(f"--stride {args.stride}: expected a whole number of frames >= 1")
    if args.stride > 1 and args.kind != "tum":
        p.error(f"--stride is for TUM sequences only (got {args.kind})")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.only != "slamkit":
        why = skip_reason(args)
        if why:
            print(f"orbslam3_side_by_side: skipped, ORB-SLAM3 is not available: {why}")
            return 0
    seq = make_sequence(args)
    out: Path = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    env = {"cpu": cpu_model(), "date_utc": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "argv": sys.argv}
    figs: list[RunFigures] = []
    nan = float("nan")
    for i in range(1, args.runs + 1):
        if args.only != "slamkit":
            d = out / f"orbslam3_run{i}"
            if args.resume and (d / "stats.json").is_file():
                n = len(seq.timestamps_s) if not args.max_frames else min(args.max_frames, len(seq.timestamps_s))
                fig = RunFigures(
                    "ORB-SLAM3", f"run{i}", str(d), n, None, None, None, 0, None, 0, None, None, nan, nan, nan
                )
                figs.append(read_orbslam3_figures(fig, seq, d))
            else:
                figs.append(run_orbslam3(args, seq, i, d))
            print(row(figs[-1]), flush=True)
        if args.only != "orbslam3" and i <= len(args.seed_list):
            seed = args.seed_list[i - 1]
            d = out / f"slamkit_seed{seed}"
            if args.resume and (d / "metrics.json").is_file():
                fig = RunFigures(
                    "slamkit", f"seed{seed}", str(d), 0, None, None, None, 0, None, 0, None, None, nan, nan, nan
                )
                figs.append(read_slamkit_figures(fig, seq, d))
            else:
                figs.append(run_slamkit(args, seq, seed, d))
            print(row(figs[-1]), flush=True)
    text = table(seq, figs, env)
    print(text)
    (out / "side_by_side.txt").write_text(text + "\n")
    report = {"env": env, "sequence": seq.name, "runs": [asdict(f) for f in figs]}
    report["medians"] = {s: medians([f for f in figs if f.system == s]) for s in ("ORB-SLAM3", "slamkit")}
    (out / "side_by_side.json").write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
