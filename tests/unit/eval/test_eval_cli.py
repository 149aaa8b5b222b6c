"""`slamkit eval` through add_eval_parser/run_eval on a small argparse parser, as slamkit/cli.py will wire it."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from matplotlib.image import imread

from slamkit.eval.cli import add_eval_parser, run_eval
from slamkit.eval.metrics import apply_sim3, compute_ate, compute_rpe
from slamkit.io.trajectory_io import write_trajectory
from slamkit.sensors import Trajectory

MakeTrajectory = Callable[..., Trajectory]  # the make_trajectory fixture (conftest.py)


def _run(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="slamkit")
    add_eval_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["eval", *argv])
    assert args.func is run_eval
    return run_eval(args)


@pytest.fixture
def pair(tmp_path: Path, make_trajectory: MakeTrajectory) -> tuple[Path, Path, Trajectory, Trajectory]:
    """A TUM ground truth and a scaled, moved, noisy TUM estimate of it (every 2nd pose)."""
    gt = make_trajectory(n=80, seed=21)
    rng = np.random.default_rng(21)
    S = np.eye(4)
    S[:3, :3] = 0.4 * np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    S[:3, 3] = [1.0, 2.0, 3.0]
    moved = apply_sim3(S, gt)
    T = moved.T_w_c[::2].copy()
    T[:, :3, 3] += rng.normal(scale=0.01, size=(40, 3))
    est = Trajectory(moved.t_s[::2] + 0.003, T)
    gt_path, est_path = tmp_path / "groundtruth.txt", tmp_path / "estimate.txt"
    write_trajectory(gt_path, gt, "tum")
    write_trajectory(est_path, est, "tum")
    return gt_path, est_path, gt, est


def test_eval_prints_table_and_writes_json_and_plot(
    pair: tuple[Path, Path, Trajectory, Trajectory], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    gt_path, est_path, gt, est = pair
    out_json, out_png = tmp_path / "res.json", tmp_path / "plot.png"
    assert _run([str(gt_path), str(est_path), "--json", str(out_json), "--plot", str(out_png)]) == 0

    ate = compute_ate(gt, est, "sim3")
    rpe = compute_rpe(gt, est, align="sim3")
    stdout = capsys.readouterr().out
    assert "40 poses matched by time, sim3 alignment" in stdout
    ate_row = next(line for line in stdout.splitlines() if line.startswith("ATE [m]"))
    assert ate_row.split()[2:] == [f"{v:.6f}" for v in (ate.rmse_m, ate.mean_m, ate.median_m, ate.max_m)]
    assert any(line.startswith("RPE [m]") and f"{rpe.rmse_m:.6f}" in line for line in stdout.splitlines())

    report = json.loads(out_json.read_text())
    assert report["ate_rmse_m"] == ate.rmse_m
    assert report["ate_mean_m"] == ate.mean_m
    assert report["ate_median_m"] == ate.median_m
    assert report["ate_max_m"] == ate.max_m
    assert report["rpe_rmse_m"] == pytest.approx(rpe.rmse_m, abs=1e-12)  # rotations went through quaternions
    assert report["align"] == "sim3"
    assert report["matched_poses"] == 40
    assert report["scale"] == pytest.approx(1.0 / 0.4, rel=1e-2)
    assert 0.005 < report["ate_rmse_m"] < 0.05  # the 1 cm noise, scaled back by 2.5

    image = imread(out_png)
    assert image.ndim == 3 and image.shape[0] > 300 and image.shape[1] > 600
    assert np.ptp(image[..., :3]) > 0.5  # something was drawn


def test_eval_se3_and_none_and_format_options(
    pair: tuple[Path, Path, Trajectory, Trajectory], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    gt_path, est_path, gt, est = pair
    out_json = tmp_path / "r.json"
    argv = [str(gt_path), str(est_path), "--align", "none", "--format", "tum", "--max-diff", "0.005"]
    assert _run([*argv, "--json", str(out_json)]) == 0
    report = json.loads(out_json.read_text())
    assert report["align"] == "none" and report["scale"] == 1.0
    assert report["ate_rmse_m"] == compute_ate(gt, est, "none").rmse_m
    # With max-diff below the 3 ms lag nothing matches: one error line, exit code 2.
    capsys.readouterr()
    assert _run([str(gt_path), str(est_path), "--max-diff", "0.001"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert err[0].startswith("slamkit eval: error: only 0 poses matched by time")
    assert str(gt_path) in err[0] and str(est_path) in err[0]


def test_eval_kitti_files_are_associated_by_index(
    tmp_path: Path, make_trajectory: MakeTrajectory, capsys: pytest.CaptureFixture[str]
) -> None:
    gt = make_trajectory(n=30, seed=22)
    est = Trajectory(gt.t_s.copy(), gt.T_w_c.copy())
    est.T_w_c[:, 0, 3] += 0.25
    write_trajectory(tmp_path / "gt.txt", gt, "kitti")
    write_trajectory(tmp_path / "est.txt", est, "kitti")
    out_json = tmp_path / "r.json"
    assert _run([str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--align", "none", "--json", str(out_json)]) == 0
    report = json.loads(out_json.read_text())
    assert report["association"] == "index" and report["gt_format"] == "kitti"
    assert report["ate_rmse_m"] == pytest.approx(0.25, abs=1e-12)
    assert "30 poses matched by index" in capsys.readouterr().out


def test_eval_bad_file_is_one_line_and_exit_2(
    pair: tuple[Path, Path, Trajectory, Trajectory], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    gt_path, _, _, _ = pair
    bad = tmp_path / "bad.txt"
    bad.write_text("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0\n")
    assert _run([str(gt_path), str(bad), "--format", "tum", "--gt-format", "tum"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"slamkit eval: error: {bad}:2: expected 8 columns (TUM trajectory 'timestamp tx ty tz qx qy qz qw'), "
        "got 7: '2.0 0 0 0 0 0 0'"
    ]

    assert _run([str(gt_path), str(tmp_path / "missing.txt")]) == 2
    assert (
        capsys.readouterr().err.strip()
        == f"slamkit eval: error: trajectory file: file {tmp_path / 'missing.txt'} does not exist"
    )

    # A plot path that is not a PNG is refused before anything is written.
    assert _run([str(gt_path), str(gt_path), "--plot", str(tmp_path / "plot.jpg")]) == 2
    assert "must end in .png" in capsys.readouterr().err
