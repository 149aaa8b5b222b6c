"""Acceptance: our ATE/RPE agree with the real evo_ape/evo_rpe commands on evo's own test files.

evo runs as a subprocess with --save_results; its stats.json (full precision) is compared to ours to 1e-6 m.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from slamkit.eval.metrics import compute_ate, compute_rpe
from slamkit.io.trajectory_io import read_trajectory

pytestmark = pytest.mark.shared_data

EVO_DATA = "eval_testdata/evo"
TUM_PAIRS = [
    ("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-ORB_kf_mono.txt"),
    ("fr2_desk_groundtruth.txt", "fr2_desk_ORB_kf_mono.txt"),
]
ALIGN_FLAGS = {"sim3": "-as", "se3": "-a"}
STATS = ("rmse", "mean", "median", "max", "min", "std")


def _evo_tool(name: str) -> str:
    """The evo console script installed beside this interpreter (evo is a dependency of slamkit)."""
    local = Path(sys.executable).parent / name
    found = str(local) if local.exists() else shutil.which(name)
    assert found, f"{name} is not installed beside {sys.executable} nor on PATH (pip install evo)"
    return found


@pytest.fixture(scope="module")
def evo_env(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """evo writes its settings under $HOME/.evo: give it a private home and a headless matplotlib."""
    env = dict(os.environ)
    env["HOME"] = str(tmp_path_factory.mktemp("evo_home"))
    env["MPLBACKEND"] = "Agg"
    return env


def _run_evo(env: dict[str, str], out_dir: Path, tool: str, *args: str) -> tuple[dict[str, float], np.ndarray]:
    """Run evo_ape/evo_rpe, return (stats, alignment Sim3) from its saved result zip."""
    zip_path = out_dir / f"{tool}.zip"
    cmd = [_evo_tool(tool), *args, "--save_results", str(zip_path), "--no_warnings"]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, f"{' '.join(cmd)} failed:\n{proc.stdout}\n{proc.stderr}"
    with zipfile.ZipFile(zip_path) as zf:
        stats = json.loads(zf.read("stats.json"))
        with zf.open("alignment_transformation_sim3.npy") as f:
            alignment = np.load(f)
    return stats, alignment


@pytest.mark.parametrize(("gt_name", "est_name"), TUM_PAIRS)
@pytest.mark.parametrize("align", ["sim3", "se3"])
def test_ate_matches_evo_ape(
    shared_datasets: Path, evo_env: dict[str, str], tmp_path: Path, gt_name: str, est_name: str, align: str
) -> None:
    gt_path, est_path = shared_datasets / EVO_DATA / gt_name, shared_datasets / EVO_DATA / est_name
    ours = compute_ate(read_trajectory(gt_path), read_trajectory(est_path), align=align)
    stats, alignment = _run_evo(evo_env, tmp_path, "evo_ape", "tum", str(gt_path), str(est_path), ALIGN_FLAGS[align])
    for key in STATS:
        assert getattr(ours, f"{key}_m") == pytest.approx(stats[key], abs=1e-6), key
    np.testing.assert_allclose(ours.alignment, alignment, atol=1e-9)
    assert ours.scale == pytest.approx(np.cbrt(np.linalg.det(alignment[:3, :3])), abs=1e-9)
    if align == "se3":
        assert ours.scale == 1.0


@pytest.mark.parametrize(("gt_name", "est_name"), TUM_PAIRS)
@pytest.mark.parametrize("align", ["sim3", "se3"])
def test_rpe_matches_evo_rpe(
    shared_datasets: Path, evo_env: dict[str, str], tmp_path: Path, gt_name: str, est_name: str, align: str
) -> None:
    gt_path, est_path = shared_datasets / EVO_DATA / gt_name, shared_datasets / EVO_DATA / est_name
    ours = compute_rpe(read_trajectory(gt_path), read_trajectory(est_path), delta=1, align=align)
    stats, _ = _run_evo(
        evo_env,
        tmp_path,
        "evo_rpe",
        "tum",
        str(gt_path),
        str(est_path),
        ALIGN_FLAGS[align],
        "--delta",
        "1",
        "--delta_unit",
        "f",
    )
    for key in STATS:
        assert getattr(ours, f"{key}_m") == pytest.approx(stats[key], abs=1e-6), key


def test_kitti_ate_matches_evo_ape_kitti(shared_datasets: Path, evo_env: dict[str, str], tmp_path: Path) -> None:
    d = shared_datasets / EVO_DATA
    gt, est = read_trajectory(d / "KITTI_00_gt.txt"), read_trajectory(d / "KITTI_00_ORB.txt")
    ours = compute_ate(gt, est, align="se3", association="index")
    stats, _ = _run_evo(
        evo_env, tmp_path, "evo_ape", "kitti", str(d / "KITTI_00_gt.txt"), str(d / "KITTI_00_ORB.txt"), "-a"
    )
    for key in STATS:
        assert getattr(ours, f"{key}_m") == pytest.approx(stats[key], abs=1e-6), key


def test_euroc_groundtruth_ate_matches_evo_ape_euroc(
    shared_datasets: Path, evo_env: dict[str, str], tmp_path: Path
) -> None:
    d = shared_datasets / EVO_DATA
    gt, est = read_trajectory(d / "V102_groundtruth.csv"), read_trajectory(d / "V102.txt")
    ours = compute_ate(gt, est, align="sim3")
    stats, _ = _run_evo(
        evo_env, tmp_path, "evo_ape", "euroc", str(d / "V102_groundtruth.csv"), str(d / "V102.txt"), "-as"
    )
    assert ours.matched_poses == 798
    for key in STATS:
        assert getattr(ours, f"{key}_m") == pytest.approx(stats[key], abs=1e-6), key
