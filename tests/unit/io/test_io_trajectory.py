"""Trajectory file I/O (slamkit.io.trajectory_io): TUM, KITTI, EuRoC round trips, real files, the errors on
bad input; ground truth at frame times (slamkit.io.ground_truth)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from evo.core.transformations import quaternion_matrix
from scipy.spatial.transform import Rotation

from slamkit.errors import ConfigError, DatasetError
from slamkit.io.ground_truth import poses_at, transform_trajectory
from slamkit.io.trajectory_io import (
    detect_format,
    read_euroc_groundtruth,
    read_kitti_poses,
    read_times,
    read_trajectory,
    read_tum_trajectory,
    write_trajectory,
)
from slamkit.sensors import Trajectory

EVO_DATA = "eval_testdata/evo"
GOOD_TUM = "1.0 0 0 0 0 0 0 1\n2.0 1 0 0 0 0 0 1\n"


def _rot_wxyz(q_wxyz: list[float]) -> np.ndarray:
    """Rotation matrix from a w x y z quaternion by evo's (Gohlke's) independent implementation."""
    return np.asarray(quaternion_matrix(np.asarray(q_wxyz, dtype=np.float64)))[:3, :3]


def make_trajectory(n: int = 10, seed: int = 0, t0_s: float = 1000.0, dt_s: float = 0.1) -> Trajectory:
    """n poses with random rotations and positions (m), one every dt_s seconds from t0_s."""
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, rng=rng).as_matrix()
    T[:, :3, 3] = rng.uniform(-5.0, 5.0, size=(n, 3))
    return Trajectory(t0_s + dt_s * np.arange(n, dtype=np.float64), T)


# ---------------------------------------------------------------------------------------------- round trips


def test_tum_round_trip_is_exact(tmp_path: Path) -> None:
    traj = make_trajectory(n=40, seed=1, t0_s=1305031102.175304)
    path = tmp_path / "est.txt"
    write_trajectory(path, traj, "tum")
    assert detect_format(path) == "tum"
    back = read_trajectory(path)
    np.testing.assert_array_equal(back.t_s, traj.t_s)
    np.testing.assert_array_equal(back.positions_m, traj.positions_m)
    np.testing.assert_allclose(back.T_w_c, traj.T_w_c, atol=1e-14)
    assert back.T_w_c.dtype == np.float64


def test_kitti_round_trip_with_times(tmp_path: Path) -> None:
    traj = make_trajectory(n=30, seed=2, t0_s=0.0, dt_s=0.1037)
    path, times = tmp_path / "00.txt", tmp_path / "times.txt"
    write_trajectory(path, traj, "kitti", times_path=times)
    assert detect_format(path) == "kitti"
    back = read_trajectory(path, "kitti", times_path=times)
    np.testing.assert_array_equal(back.t_s, traj.t_s)
    np.testing.assert_array_equal(back.T_w_c, traj.T_w_c)  # 12 numbers written with full precision


def test_kitti_without_times_uses_line_index(tmp_path: Path) -> None:
    traj = make_trajectory(n=7)
    path = tmp_path / "poses.txt"
    write_trajectory(path, traj, "kitti")
    back = read_trajectory(path)
    np.testing.assert_array_equal(back.t_s, np.arange(7.0))


def test_euroc_round_trip(tmp_path: Path) -> None:
    traj = make_trajectory(n=25, seed=3, t0_s=1403715524.907143, dt_s=0.005)
    path = tmp_path / "data.csv"
    write_trajectory(path, traj, "euroc")
    text = path.read_text().splitlines()
    assert text[0].startswith("#timestamp")
    first = text[1].split(",")
    assert len(first) == 8 and first[0].isdigit()  # integer nanoseconds
    assert detect_format(path) == "euroc"
    back = read_trajectory(path)
    # Nanosecond stamps near 1.4e18 are not exact in float64 seconds (spacing 2.4e-7 s).
    np.testing.assert_allclose(back.t_s, traj.t_s, rtol=0, atol=5e-7)
    np.testing.assert_allclose(back.T_w_c, traj.T_w_c, atol=1e-14)


# ---------------------------------------------------------------------------------------------- real files


def test_reads_real_tum_groundtruth(shared_datasets: Path) -> None:
    path = shared_datasets / EVO_DATA / "freiburg1_xyz-groundtruth.txt"
    assert detect_format(path) == "tum"
    traj = read_trajectory(path)
    assert len(traj) == 3000
    # First data line (after three '#' lines): 1305031098.6659 1.3563 0.6305 1.6380 0.6132 0.5962 -0.3311 -0.3986
    assert traj.t_s[0] == 1305031098.6659
    np.testing.assert_array_equal(traj.T_w_c[0, :3, 3], [1.3563, 0.6305, 1.6380])
    q_wxyz = np.array([-0.3986, 0.6132, 0.5962, -0.3311])
    np.testing.assert_allclose(traj.T_w_c[0, :3, :3], _rot_wxyz(list(q_wxyz)), atol=1e-12)
    np.testing.assert_array_equal(traj.T_w_c[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (3000, 1)))


def test_reads_real_tum_with_a_repeated_timestamp(shared_datasets: Path) -> None:
    # fr2_desk ground truth repeats the stamp 1311868229.5760 once: allowed (non-decreasing), as evo does.
    traj = read_trajectory(shared_datasets / EVO_DATA / "fr2_desk_groundtruth.txt")
    assert len(traj) == 20957
    assert np.count_nonzero(np.diff(traj.t_s) == 0) == 1


def test_reads_real_euroc_groundtruth(shared_datasets: Path) -> None:
    path = shared_datasets / EVO_DATA / "V102_groundtruth.csv"
    assert detect_format(path) == "euroc"
    traj = read_trajectory(path)
    assert len(traj) == 16702
    # 1403715524907143168,0.515356,1.996773,0.971104,0.161996,0.789985,-0.205376,0.554528,...
    assert traj.t_s[0] == pytest.approx(1403715524.907143168, abs=1e-6)
    assert traj.t_s[1] - traj.t_s[0] == pytest.approx(0.005, abs=1e-6)
    np.testing.assert_array_equal(traj.T_w_c[0, :3, 3], [0.515356, 1.996773, 0.971104])
    np.testing.assert_allclose(traj.T_w_c[0, :3, :3], _rot_wxyz([0.161996, 0.789985, -0.205376, 0.554528]), atol=1e-12)


def test_reads_real_kitti_with_times(shared_datasets: Path) -> None:
    d = shared_datasets / EVO_DATA
    traj = read_trajectory(d / "KITTI_00_gt.txt", "auto", times_path=d / "KITTI_00_gt_times.txt")
    assert len(traj) == 4541
    assert traj.t_s[1] == 1.037359e-01
    # Line 2: 9.999978e-01 5.272628e-04 -2.066935e-03 -4.690294e-02 ... 8.586941e-01
    np.testing.assert_array_equal(traj.T_w_c[1, 0], [9.999978e-01, 5.272628e-04, -2.066935e-03, -4.690294e-02])
    assert traj.T_w_c[1, 2, 3] == 8.586941e-01


def test_detects_euroc_from_header_and_tum_with_comments(tmp_path: Path) -> None:
    euroc = tmp_path / "gt.csv"
    euroc.write_text(
        "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []\n"
    )
    # A header alone is recognised as EuRoC, then reported as having no poses.
    with pytest.raises(DatasetError, match=r"gt\.csv: no poses"):
        read_trajectory(euroc)
    assert detect_format(euroc) == "euroc"
    tum = tmp_path / "est.txt"
    tum.write_text("# comment\n\n1.0 0 0 0 0 0 0 1.004\n2.0 1 0 0 0 0 0 1\n")
    assert detect_format(tum) == "tum"
    traj = read_trajectory(tum)
    np.testing.assert_array_equal(traj.T_w_c[0], np.eye(4))  # quaternion (0,0,0,1.004): within 1e-2, normalised
    assert isinstance(traj, Trajectory)


def test_read_times(tmp_path: Path) -> None:
    p = tmp_path / "times.txt"
    p.write_text("0.000000e+00\n1.037359e-01\n2.073381e-01\n")
    np.testing.assert_array_equal(read_times(p), [0.0, 0.1037359, 0.2073381])
    # Frame times: a repeated time is an error (unlike trajectory stamps), as is an empty file.
    p.write_text("0.0\n0.1\n0.1\n")
    with pytest.raises(DatasetError, match=r"times\.txt:3: KITTI times must be strictly increasing"):
        read_times(p)
    p.write_text("# nothing\n")
    with pytest.raises(DatasetError, match=r"times\.txt: no timestamps in the file"):
        read_times(p)


def test_repeated_trajectory_timestamp_is_accepted(tmp_path: Path) -> None:
    p = tmp_path / "gt.txt"
    p.write_text(GOOD_TUM + "2.0 2 0 0 0 0 0 1\n3.0 3 0 0 0 0 0 1\n")
    traj = read_tum_trajectory(p)
    np.testing.assert_array_equal(traj.t_s, [1.0, 2.0, 2.0, 3.0])
    np.testing.assert_array_equal(traj.positions_m[:, 0], [0.0, 1.0, 2.0, 3.0])


# ---------------------------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("content", "fmt", "match"),
    [
        (GOOD_TUM + "3.0 1 0 0 0 0 1\n", "tum", r"bad\.txt:3: expected 8 columns \(TUM trajectory .*got 7"),
        (GOOD_TUM + "3.0 1 0 zero 0 0 0 1\n", "tum", r"bad\.txt:3: column 4 should be a number .*got 'zero'"),
        (GOOD_TUM + "3.0 1 0 nan 0 0 0 1\n", "tum", r"bad\.txt:3: column 4 should be finite"),
        (GOOD_TUM + "1.5 1 0 0 0 0 0 1\n", "tum", r"bad\.txt:3: .*must be non-decreasing; 1\.5 follows 2\.0 on line 2"),
        ("# c\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0 0\n", "tum", r"bad\.txt:3: quaternion norm is 0\.0000"),
        ("1.0 0 0 0 0 0 0 0.5\n", "tum", r"bad\.txt:1: quaternion norm is 0\.5000; expected a unit quaternion"),
        ("1.0 0 0 0 0 0 0 1.02\n", "tum", r"bad\.txt:1: quaternion norm is 1\.0200"),
        ("", "tum", r"bad\.txt: no poses in the file"),
        ("# only a comment\n\n", "auto", r"bad\.txt: no poses in the file"),
        ("1 2 3 4 5\n", "auto", r"bad\.txt:1: cannot tell the trajectory format from 5 columns"),
        ("1 0 0 0 0 1 0 0 0 0 1\n", "kitti", r"bad\.txt:1: expected 12 columns \(KITTI pose.*got 11"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n2 0 0 0 0 1 0 0 0 0 1 0\n", "kitti", r"bad\.txt:2: the 3x3 block is not a rotation"),
        ("1 0 0 0 0 1 0 0 0 0 -1 0\n", "kitti", r"bad\.txt:1: the 3x3 block is not a rotation .*det = -1"),
        ("#t\n1,0,0,0,1,0,0,0,9\n2,0,0,0,1,0,0,0\n", "euroc", r"bad\.txt:3: expected 9 columns like line 2 .*got 8"),
        ("#t\n1,0,0,0,1,0,0,0\n2,0,0,0,1,0,0\n", "euroc", r"bad\.txt:3: expected at least 8 columns"),
        ("#t\nabc,0,0,0,1,0,0,0\n", "euroc", r"bad\.txt:2: column 1 should be an integer .*got 'abc'"),
        ("#t\n1,0,0,0,0,0,0,0\n", "euroc", r"bad\.txt:2: quaternion norm is 0\.0000"),
        ("#t\n2,0,0,0,1,0,0,0\n1,0,0,0,1,0,0,0\n", "euroc", r"bad\.txt:3: ground-truth timestamps must be non-dec"),
        ("1,0,0,0,1,0\n", "auto", r"bad\.txt:1: expected at least 8 columns \(EuRoC ground truth"),
    ],
)
def test_bad_input_names_file_line_and_expectation(tmp_path: Path, content: str, fmt: str, match: str) -> None:
    path = tmp_path / "bad.txt"
    path.write_text(content)
    with pytest.raises(DatasetError, match=match):
        read_trajectory(path, fmt)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match=r"trajectory file: file .*nope\.txt does not exist"):
        read_trajectory(tmp_path / "nope.txt")


def test_kitti_times_count_mismatch(tmp_path: Path) -> None:
    path, times = tmp_path / "poses.txt", tmp_path / "times.txt"
    write_trajectory(path, make_trajectory(n=5), "kitti")
    times.write_text("0\n0.1\n0.2\n")
    with pytest.raises(DatasetError, match=r"times\.txt: 3 timestamps but .*poses\.txt has 5 poses"):
        read_trajectory(path, times_path=times)


def test_bad_format_names_are_config_errors(tmp_path: Path) -> None:
    path = tmp_path / "x.txt"
    path.write_text(GOOD_TUM)
    with pytest.raises(ConfigError, match=r"fmt='g2o' .*expected one of"):
        read_trajectory(path, "g2o")
    with pytest.raises(ConfigError, match=r"fmt='auto'"):
        write_trajectory(path, make_trajectory(n=3), "auto")
    with pytest.raises(ConfigError, match="times_path is only for KITTI"):
        read_trajectory(path, "tum", times_path=path)


def test_write_refuses_non_finite_pose(tmp_path: Path) -> None:
    traj = make_trajectory(n=4)
    T = traj.T_w_c.copy()
    T[2, 0, 3] = np.nan
    with pytest.raises(DatasetError, match=r"out\.txt: pose 2 has a non-finite"):
        write_trajectory(tmp_path / "out.txt", Trajectory(traj.t_s, T), "tum")
    assert not (tmp_path / "out.txt").exists()


# ---------------------------------------------------------------------------------------------- dataset readers


def test_tum_trajectory_rotation_and_position(tmp_path: Path) -> None:
    q = Rotation.from_euler("z", 90, degrees=True).as_quat()  # x y z w
    p = tmp_path / "gt.txt"
    p.write_text(f"# t x y z qx qy qz qw\n1.0 1 2 3 {q[0]} {q[1]} {q[2]} {q[3]}\n2.0 0 0 0 0 0 0 1\n")
    traj = read_tum_trajectory(p)
    np.testing.assert_allclose(traj.T_w_c[0, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(traj.positions_m[0], [1, 2, 3])
    back = tmp_path / "back.txt"
    back.write_text("2.0 0 0 0 0 0 0 1\n1.0 0 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"back\.txt:2: trajectory timestamps must be non-decreasing"):
        read_tum_trajectory(back)


def test_euroc_groundtruth_quaternion_is_w_first_and_extra_columns_ignored(tmp_path: Path) -> None:
    p = tmp_path / "data.csv"
    p.write_text("#t,px,py,pz,qw,qx,qy,qz\n1000000000,1,2,3,0.7071068,0,0,0.7071068,9,9\n")
    traj = read_euroc_groundtruth(p)
    assert traj.t_s[0] == 1.0
    np.testing.assert_allclose(traj.T_w_c[0, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-6)
    short = tmp_path / "short.csv"
    short.write_text("1000000000,1,2,3\n")
    with pytest.raises(DatasetError, match=r"short\.csv:1: expected at least 8 columns"):
        read_euroc_groundtruth(short)


def test_kitti_poses_need_one_time_per_pose(tmp_path: Path) -> None:
    poses, times = tmp_path / "07.txt", tmp_path / "times.txt"
    poses.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 3)
    times.write_text("0.0\n0.1\n")
    with pytest.raises(DatasetError, match=r"times\.txt: 2 timestamps but .*07\.txt has 3 poses"):
        read_kitti_poses(poses, times)
    times.write_text("0.0\n0.1\n0.2\n")
    np.testing.assert_array_equal(read_kitti_poses(poses, times).t_s, [0.0, 0.1, 0.2])
    np.testing.assert_array_equal(read_kitti_poses(poses).t_s, [0.0, 1.0, 2.0])


def test_transform_trajectory_right_multiplies() -> None:
    traj = make_trajectory(n=3, seed=4)
    T_b_c = make_trajectory(n=1, seed=5).T_w_c[0]
    out = transform_trajectory(traj, T_b_c)
    np.testing.assert_allclose(out.T_w_c[1], traj.T_w_c[1] @ T_b_c, atol=1e-15)
    np.testing.assert_array_equal(out.t_s, traj.t_s)


def test_poses_at_interpolates_and_respects_gaps() -> None:
    T = np.tile(np.eye(4), (3, 1, 1))
    T[1, :3, 3] = [1.0, 0.0, 0.0]
    T[1, :3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    T[2, :3, 3] = [5.0, 0.0, 0.0]
    traj = Trajectory(np.array([0.0, 1.0, 3.0]), T)
    out = poses_at(traj, np.array([0.25, 1.0, 2.0, -1.0]), max_gap_s=1.5)
    assert out[0] is not None and out[1] is not None
    np.testing.assert_allclose(out[0][:3, 3], [0.25, 0, 0])
    np.testing.assert_allclose(Rotation.from_matrix(out[0][:3, :3]).as_euler("xyz", degrees=True), [0, 0, 22.5])
    np.testing.assert_array_equal(out[1], T[1])
    assert out[2] is None  # bracketing samples 2 s apart > 1.5 s
    assert out[3] is None  # before the first sample


def test_poses_at_with_a_repeated_stamp() -> None:
    T = np.tile(np.eye(4), (4, 1, 1))
    T[:, 0, 3] = [0.0, 1.0, 1.5, 3.0]
    traj = Trajectory(np.array([0.0, 1.0, 1.0, 2.0]), T)
    out = poses_at(traj, np.array([1.0, 1.5, 0.5]), max_gap_s=1.5)
    assert out[0] is not None and out[1] is not None and out[2] is not None
    assert out[0][0, 3] == 1.0  # the first sample of the repeated stamp
    assert out[1][0, 3] == pytest.approx(2.25)  # between the second (1.5 m at 1 s) and 3 m at 2 s
    assert out[2][0, 3] == pytest.approx(0.5)
