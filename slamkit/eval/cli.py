"""``slamkit eval GROUNDTRUTH ESTIMATE``: ATE and RPE of an estimated trajectory, as evo_ape/evo_rpe compute them.

``add_eval_parser(subparsers)`` registers the subcommand (its handler is ``args.func = run_eval``);
``run_eval(args)`` prints a table and returns the exit code: 0 on success, 2 on bad input (one line on stderr).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from slamkit.errors import SlamkitError

EXIT_OK = 0
EXIT_BAD_INPUT = 2
_FORMATS = ("auto", "tum", "kitti", "euroc")


def add_eval_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register the ``eval`` subcommand on an argparse ``_SubParsersAction`` and return its parser."""
    p: argparse.ArgumentParser = subparsers.add_parser(
        "eval",
        help="ATE/RPE of an estimated trajectory against ground truth (evo as the engine)",
        description=(
            "Absolute trajectory error (after Umeyama alignment) and relative pose error of ESTIMATE against "
            "GROUNDTRUTH; poses are associated by timestamp (by index for KITTI files without times)."
        ),
    )
    p.add_argument("groundtruth", type=Path, metavar="GROUNDTRUTH", help="ground-truth trajectory file")
    p.add_argument("estimate", type=Path, metavar="ESTIMATE", help="estimated trajectory file")
    p.add_argument(
        "--align",
        choices=("sim3", "se3", "none"),
        default="sim3",
        help="Umeyama alignment of the estimate: sim3 (with scale, monocular; evo -as), se3 (evo -a), none",
    )
    p.add_argument(
        "--format",
        choices=_FORMATS,
        default="auto",
        help="format of ESTIMATE, and of GROUNDTRUTH unless --gt-format is given (default: detect)",
    )
    p.add_argument("--gt-format", choices=_FORMATS, default=None, help="format of GROUNDTRUTH")
    p.add_argument("--gt-times", type=Path, default=None, help="times.txt for a KITTI GROUNDTRUTH")
    p.add_argument("--est-times", type=Path, default=None, help="times.txt for a KITTI ESTIMATE")
    p.add_argument(
        "--max-diff",
        type=float,
        default=0.01,
        help="max. timestamp difference in seconds to associate two poses (default: 0.01)",
    )
    p.add_argument("--delta", type=int, default=1, help="RPE step in frames (default: 1)")
    p.add_argument("--json", type=Path, default=None, metavar="FILE", help="write the results as JSON")
    p.add_argument("--plot", type=Path, default=None, metavar="FILE.png", help="plot the aligned estimate over GT")
    p.set_defaults(func=run_eval)
    return p


def _table(rows: list[tuple[str, list[float]]], header: list[str]) -> str:
    width = max(len(name) for name, _ in rows)
    lines = [" " * width + "".join(f"{h:>12}" for h in header)]
    lines += [name.ljust(width) + "".join(f"{v:12.6f}" for v in vals) for name, vals in rows]
    return "\n".join(lines)


def run_eval(args: argparse.Namespace) -> int:
    """Run ``slamkit eval`` with parsed arguments; returns the process exit code."""
    try:
        return _run(args)
    except (SlamkitError, OSError) as exc:
        print(f"slamkit eval: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT


def _run(args: argparse.Namespace) -> int:
    # Imported here so that registering the subcommand does not load evo and matplotlib for every command.
    from slamkit.eval.metrics import apply_sim3, compute_ate, compute_rpe
    from slamkit.io.trajectory_io import detect_format, read_trajectory

    gt_path: Path = args.groundtruth
    est_path: Path = args.estimate
    gt_fmt = args.gt_format or args.format
    gt_fmt = detect_format(gt_path) if gt_fmt == "auto" else gt_fmt
    est_fmt = detect_format(est_path) if args.format == "auto" else args.format
    gt = read_trajectory(gt_path, gt_fmt, times_path=args.gt_times)
    est = read_trajectory(est_path, est_fmt, times_path=args.est_times)
    # A KITTI file without times.txt has index timestamps: only association by index is meaningful.
    by_index = (gt_fmt == "kitti" and args.gt_times is None) or (est_fmt == "kitti" and args.est_times is None)
    association = "index" if by_index else "time"
    gt_name, est_name = str(gt_path), str(est_path)
    ate = compute_ate(gt, est, args.align, args.max_diff, association=association, gt_name=gt_name, est_name=est_name)
    rpe = compute_rpe(
        gt,
        est,
        args.delta,
        "frames",
        args.align,
        args.max_diff,
        association=association,
        gt_name=gt_name,
        est_name=est_name,
    )

    print(
        f"{est_path} ({est_fmt}) vs {gt_path} ({gt_fmt}): {ate.matched_poses} poses matched by "
        f"{association}, {args.align} alignment, scale {ate.scale:.6f}"
    )
    print(
        _table(
            [
                ("ATE [m]", [ate.rmse_m, ate.mean_m, ate.median_m, ate.max_m]),
                (f"RPE [m] (delta {args.delta} frames)", [rpe.rmse_m, rpe.mean_m, rpe.median_m, rpe.max_m]),
                ("RPE [deg]", [rpe.rot_rmse_deg, rpe.rot_mean_deg, rpe.rot_median_deg, rpe.rot_max_deg]),
            ],
            ["rmse", "mean", "median", "max"],
        )
    )

    if args.json is not None:
        report = {
            "groundtruth": str(gt_path),
            "estimate": str(est_path),
            "gt_format": gt_fmt,
            "est_format": est_fmt,
            "association": association,
            "max_diff_s": args.max_diff,
            "align": args.align,
            "scale": ate.scale,
            "alignment_sim3": ate.alignment.tolist(),
            "matched_poses": ate.matched_poses,
            "ate_rmse_m": ate.rmse_m,
            "ate_mean_m": ate.mean_m,
            "ate_median_m": ate.median_m,
            "ate_max_m": ate.max_m,
            "ate_min_m": ate.min_m,
            "ate_std_m": ate.std_m,
            "rpe_delta_frames": args.delta,
            "rpe_pairs": rpe.num_pairs,
            "rpe_rmse_m": rpe.rmse_m,
            "rpe_mean_m": rpe.mean_m,
            "rpe_median_m": rpe.median_m,
            "rpe_max_m": rpe.max_m,
            "rpe_rot_rmse_deg": rpe.rot_rmse_deg,
            "rpe_rot_mean_deg": rpe.rot_mean_deg,
        }
        args.json.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
        print(f"wrote {args.json}")

    if args.plot is not None:
        from slamkit.eval.plot import plot_trajectories

        title = f"{est_path.name} vs {gt_path.name}: ATE rmse {ate.rmse_m:.4f} m ({args.align})"
        plot_trajectories(args.plot, gt, apply_sim3(ate.alignment, est), title=title)
        print(f"wrote {args.plot}")
    return EXIT_OK
