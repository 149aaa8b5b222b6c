"""ATE (Sim3) of two sessions of a sequence (docs/atlas.md, "Multi-session"; docs/BENCHMARKS.md).

Usage: python benchmarks/multisession_ate.py FIRST_RUN_DIR SECOND_RUN_DIR GROUND_TRUTH.tum

"before": the first run's trajectory.tum joined with the second run's own frames (those after the first run's last
timestamp): the first session's frames as its run wrote them. "after": the second run's trajectory.tum alone (both
sessions' frames, placed against the keyframes as the second session left them). "KF both": the second run's
keyframes.tum. Each one Sim3 alignment against the ground truth (TUM file: t x y z qx qy qz qw).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from slamkit.eval.metrics import compute_ate
from slamkit.io.trajectory_io import read_trajectory
from slamkit.sensors import Trajectory


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("first", type=Path)
    parser.add_argument("second", type=Path)
    parser.add_argument("ground_truth", type=Path)
    args = parser.parse_args()
    gt = read_trajectory(args.ground_truth, "tum")
    first = read_trajectory(args.first / "trajectory.tum", "tum")
    second = read_trajectory(args.second / "trajectory.tum", "tum")
    own = second.t_s > first.t_s.max() + 1e-6
    t = np.concatenate([first.t_s, second.t_s[own]])
    order = np.argsort(t, kind="stable")
    joined = Trajectory(t[order], np.concatenate([first.T_w_c, second.T_w_c[own]])[order])
    before = compute_ate(gt, joined, align="sim3")
    after = compute_ate(gt, second, align="sim3")
    kf = compute_ate(gt, read_trajectory(args.second / "keyframes.tum", "tum"), align="sim3")
    alone = compute_ate(gt, first, align="sim3")
    print(
        f"first run alone {alone.rmse_m * 100:.2f} cm ({len(first)} frames); second run's own frames {int(own.sum())}"
    )
    print(
        f"before (two files joined) {before.rmse_m * 100:.2f} cm ({before.matched_poses} poses); after (second "
        f"trajectory.tum) {after.rmse_m * 100:.2f} cm ({after.matched_poses} poses); KF both {kf.rmse_m * 100:.2f} cm"
    )


if __name__ == "__main__":
    main()
