"""benchmarks/orbslam3_side_by_side.py: the figures it reads from each system's outputs, and its skip."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

SCRIPT = Path(__file__).resolve().parents[3] / "benchmarks" / "orbslam3_side_by_side.py"
N_FRAMES = 30
FPS = 30.0


def load_script() -> ModuleType:
    spec = importlib.util.spec_from_file_location("orbslam3_side_by_side", SCRIPT)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses resolve their annotations through sys.modules
    spec.loader.exec_module(module)
    return module


def tum_line(t: float, p: np.ndarray, q: np.ndarray) -> str:
    return f"{t:.6f} {p[0]:.9f} {p[1]:.9f} {p[2]:.9f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}"


def ground_truth(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(n,) s timestamps, (n, 3) m camera centres on a curve, (n, 4) xyzw quaternions."""
    t = 100.0 + np.arange(n) / FPS
    a = np.linspace(0.0, 1.5, n)
    p = np.stack([np.cos(a), np.sin(a), 0.1 * a], axis=1)
    q = Rotation.from_euler("z", a[:, None]).as_quat()
    return t, p, q


def write_estimate(path: Path, frames: list[int], noise_m: float = 0.0) -> None:
    """The ground truth at ``frames`` seen through a similarity (scale 0.3, a rotation, a shift), as a
    monocular system's trajectory is; ``noise_m`` moves every other pose by that much (in GT metres)."""
    t, p, q = ground_truth(N_FRAMES)
    R = Rotation.from_euler("xyz", [0.3, -0.2, 1.0])
    lines = []
    for j, i in enumerate(frames):
        pi = p[i] + (noise_m if j % 2 else 0.0) * np.array([1.0, 0.0, 0.0])
        pe = 0.3 * R.apply(pi) + np.array([2.0, -1.0, 0.5])
        qe = (R * Rotation.from_quat(q[i])).as_quat()
        lines.append(tum_line(t[i], pe, qe))
    path.write_text("\n".join(lines) + "\n")


@pytest.fixture
def sequence(tmp_path: Path) -> Path:
    """A TUM-format sequence folder: rgb.txt (N_FRAMES names) and groundtruth.txt."""
    seq = tmp_path / "rgbd_dataset_freiburg1_fake"
    seq.mkdir()
    t, p, q = ground_truth(N_FRAMES)
    (seq / "rgb.txt").write_text("# colour images\n" + "".join(f"{ti:.6f} rgb/{ti:.6f}.png\n" for ti in t))
    (seq / "groundtruth.txt").write_text("# t x y z qx qy qz qw\n" + "\n".join(map(tum_line, t, p, q)) + "\n")
    return seq


def test_orbslam3_figures_init_frame_tracking_and_sim3_ate(sequence: Path, tmp_path: Path) -> None:
    sbs = load_script()
    seq = sbs.make_sequence(sbs.parse_args(["tum", str(sequence), "--out", str(tmp_path / "out")]))
    out = tmp_path / "orb"
    out.mkdir()
    # Initialised at frame 4, lost at frames 10 and 11: 24 of the 26 frames from 4 on have a pose.
    tracked = [i for i in range(4, N_FRAMES) if i not in (10, 11)]
    write_estimate(out / "traj_online.txt", tracked)
    write_estimate(out / "traj.txt", tracked)
    write_estimate(out / "kf_traj.txt", tracked[::3], noise_m=0.02)
    (out / "stats.json").write_text(json.dumps({"fps_loop": 25.0, "track_ms_median": 31.5}))
    fig = sbs.RunFigures("ORB-SLAM3", "run1", str(out), N_FRAMES, None, None, None, 0, None, 0, None, None, 1, 0, 0)
    fig = sbs.read_orbslam3_figures(fig, seq, out)
    assert fig.error == ""
    assert fig.init_frame == 4
    assert fig.tracked_pct == pytest.approx(100.0 * 24 / 26)
    # A similarity of the ground truth: Sim3 alignment removes it exactly.
    assert fig.ate_all_m == pytest.approx(0.0, abs=1e-6)
    assert fig.ate_all_poses == 24
    # Every other keyframe 2 cm off: the RMSE is about 1 cm (the alignment spreads it a little).
    assert 0.005 < fig.ate_kf_m < 0.015
    assert (fig.fps, fig.track_ms) == (25.0, 31.5)


def test_slamkit_figures_from_a_run_directory(sequence: Path, tmp_path: Path) -> None:
    sbs = load_script()
    seq = sbs.make_sequence(sbs.parse_args(["tum", str(sequence), "--out", str(tmp_path / "out")]))
    out = tmp_path / "sk"
    out.mkdir()
    t, _, _ = ground_truth(N_FRAMES)
    states = ["not_initialized"] * 6 + ["ok"] * 20 + ["lost"] * 4
    rows = [f"{i},{t[i]:.6f},{s},x,1000,0,10.0," for i, s in enumerate(states)]
    (out / "frames.csv").write_text(
        "frame,timestamp_s,state,method,features,inliers,track_ms,message\n" + "\n".join(rows)
    )
    (out / "metrics.json").write_text(json.dumps({"wall_s": 3.0, "tracking_ms_median": 40.0}))
    write_estimate(out / "trajectory.tum", list(range(6, 26)))
    write_estimate(out / "keyframes.tum", list(range(6, 26, 4)))
    fig = sbs.RunFigures("slamkit", "seed0", str(out), 0, None, None, None, 0, None, 0, None, None, 1, 0, 0)
    fig = sbs.read_slamkit_figures(fig, seq, out)
    assert fig.init_frame == 6
    assert fig.tracked_pct == pytest.approx(100.0 * 20 / 24)
    assert fig.ate_all_m == pytest.approx(0.0, abs=1e-6) and fig.ate_kf_m == pytest.approx(0.0, abs=1e-6)
    assert fig.fps == pytest.approx(N_FRAMES / 3.0)
    medians = sbs.medians([fig])
    assert medians["init_frame"] == 6 and medians["track_ms"] == 40.0


def test_skips_with_a_reason_when_orbslam3_is_absent(
    sequence: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    sbs = load_script()
    assert sbs.main(["tum", str(sequence), "--peers", str(tmp_path / "no_peers"), "--out", str(tmp_path / "o")]) == 0
    assert "skipped, ORB-SLAM3 is not available" in capsys.readouterr().out
    assert not (tmp_path / "o").exists()


def test_slamkit_overrides_after_a_double_dash(tmp_path: Path) -> None:
    sbs = load_script()
    args = sbs.parse_args(
        ["kitti", str(tmp_path), "--runs", "2", "--out", str(tmp_path / "o"), "--", "+experiment=kitti07"]
    )
    assert args.overrides == ["+experiment=kitti07"] and args.seed_list == [0, 1] and args.sequence == "07"


def test_a_stride_gives_both_systems_every_nth_frame_of_the_sequence(sequence: Path, tmp_path: Path) -> None:
    """``--stride 3`` (TUM): a sequence folder whose rgb.txt lists frames 0, 3, 6, ... of the original, read alike by
    slamkit's TUM reader, with the original's ground truth; a stride on KITTI or below 1 is refused."""
    import cv2

    from slamkit.io.tum_rgbd import TumRgbdDataset

    sbs = load_script()
    (sequence / "rgb").mkdir()
    t, _, _ = ground_truth(N_FRAMES)
    for ti in t:
        cv2.imwrite(str(sequence / "rgb" / f"{ti:.6f}.png"), np.full((8, 8), 128, np.uint8))
    seq = sbs.make_sequence(sbs.parse_args(["tum", str(sequence), "--stride", "3", "--out", str(tmp_path / "out")]))
    assert seq.orb_seq != sequence and seq.orb_seq.name == sequence.name  # the camera comes from the folder name
    assert seq.timestamps_s == pytest.approx(t[::3].tolist(), abs=1e-6)
    assert seq.gt == (sequence / "groundtruth.txt").resolve() and "every 3th frame" in seq.name
    assert f"dataset.root={seq.orb_seq}" in seq.slamkit_overrides
    reader = TumRgbdDataset(root=str(seq.orb_seq), use_depth=False)
    assert reader.timestamps() == pytest.approx(t[::3], abs=1e-6)
    assert (seq.orb_seq / "rgb").resolve() == (sequence / "rgb").resolve()
    for bad in (["tum", str(sequence), "--stride", "0"], ["kitti", str(tmp_path), "--stride", "2"]):
        with pytest.raises(SystemExit):
            sbs.parse_args([*bad, "--out", str(tmp_path / "o")])
