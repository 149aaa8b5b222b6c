"""EuRoC reader on the shared V1_01_easy slice (95 stereo frames, IMU, TUM-format ground truth)."""

from __future__ import annotations

import itertools
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slamkit.errors import CalibrationError, DatasetError
from slamkit.geometry.camera import PinholeCamera
from slamkit.interfaces import Dataset
from slamkit.io.euroc import EurocDataset

V101 = "euroc/V1_01_easy"
T_BS_CAM0 = np.array(
    [
        [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
        [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
        [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
        [0.0, 0.0, 0.0, 1.0],
    ]
)


@pytest.fixture(scope="module")
def root(shared_datasets: Path) -> Path:
    return shared_datasets / V101


@pytest.fixture(scope="module")
def stereo(root: Path) -> EurocDataset:
    return EurocDataset(root=root, stereo=True, groundtruth=str(root / "extra/V101_gt_evo_tum_format.txt"))


def _copy_mav0(src: Path, dst: Path) -> Path:
    """Writable copy of the text files; image folders are symlinked (read-only, large)."""
    for p in src.rglob("*"):
        rel = p.relative_to(src)
        if p.is_dir() and p.name == "data":
            (dst / rel).parent.mkdir(parents=True, exist_ok=True)
            (dst / rel).symlink_to(p)
        elif p.is_file() and "data" not in rel.parts[:-1]:
            (dst / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(p, dst / rel)
    return dst


def test_frames_intrinsics_and_size(stereo: EurocDataset) -> None:
    assert isinstance(stereo, Dataset)
    assert len(stereo) == 95
    assert stereo.timestamps()[0] == pytest.approx(1403715273.262142976, abs=1e-6)
    assert stereo.fps == 20.0
    cam = stereo.camera
    assert (cam.width, cam.height) == (752, 480)
    np.testing.assert_allclose(cam.K, [[458.654, 0.0, 367.215], [0.0, 457.296, 248.375], [0.0, 0.0, 1.0]])
    assert isinstance(cam, PinholeCamera)
    np.testing.assert_allclose(cam.dist[:4], np.array([-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]))
    f = stereo[0]
    assert f.image.shape == (480, 752) and f.color is None
    assert f.source.endswith("cam0/data/1403715273262142976.png")
    assert stereo.T_b_c is not None
    np.testing.assert_allclose(stereo.T_b_c, T_BS_CAM0)


def test_stereo_right_image_and_baseline(stereo: EurocDataset) -> None:
    f = stereo[10]
    assert f.image_right is not None and f.image_right.shape == (480, 752)
    assert not np.array_equal(f.image, f.image_right)
    assert stereo.T_l_r is not None and stereo.camera_right is not None
    assert stereo.camera_right.K[0, 2] == 379.999
    # VI-Sensor baseline ~11 cm along the left camera's +x axis.
    assert stereo.T_l_r[0, 3] == pytest.approx(0.110074, abs=1e-5)
    assert np.linalg.norm(stereo.T_l_r[:3, 3]) == pytest.approx(0.11008, abs=1e-4)


def test_imu_samples_between_frames(stereo: EurocDataset, root: Path) -> None:
    imu_ns = np.loadtxt(root / "mav0/imu0/data.csv", delimiter=",", skiprows=1, usecols=0, dtype=np.int64)
    cam_ns = np.loadtxt(root / "mav0/cam0/data.csv", delimiter=",", skiprows=1, usecols=0, dtype=np.int64)
    frames = list(stereo)
    counts = [len(f.imu) for f in frames[1:]]
    assert all(c == 10 for c in counts)  # 200 Hz IMU, 20 Hz camera
    assert sum(counts) == int(np.count_nonzero((imu_ns > cam_ns[0]) & (imu_ns <= cam_ns[-1])))
    for prev, f in itertools.pairwise(frames):
        assert np.all(f.imu.t_s > prev.timestamp_s) and np.all(f.imu.t_s <= f.timestamp_s)
    # Columns: gyro first, then acc. At rest the accelerometer reads ~9.81 m/s^2, the gyro ~0.
    acc = np.concatenate([f.imu.acc_mps2 for f in frames])
    gyro = np.concatenate([f.imu.gyro_radps for f in frames])
    assert np.linalg.norm(acc.mean(axis=0)) == pytest.approx(9.81, abs=0.3)
    assert np.linalg.norm(gyro.mean(axis=0)) < 0.15  # (mostly the gyro bias)
    np.testing.assert_allclose(
        frames[0].imu.gyro_radps[0], [-0.0020943951023931952, 0.017453292519943295, 0.07749261878854824]
    )


def test_ground_truth_is_cam0_pose(stereo: EurocDataset, root: Path) -> None:
    gt = np.loadtxt(root / "extra/V101_gt_evo_tum_format.txt")
    T_w_b = np.eye(4)
    T_w_b[:3, :3] = Rotation.from_quat(gt[0, 4:8]).as_matrix()
    T_w_b[:3, 3] = gt[0, 1:4]
    assert stereo.ground_truth is not None
    np.testing.assert_allclose(stereo.ground_truth.T_w_c[0], T_w_b @ T_BS_CAM0, atol=1e-12)
    frames = list(stereo)
    assert all(f.T_w_c_gt is not None for f in frames)
    f0 = frames[0]
    assert f0.T_w_c_gt is not None
    np.testing.assert_allclose(f0.T_w_c_gt, T_w_b @ T_BS_CAM0, atol=1e-4)  # interpolated 3 us later
    # Physical check of the conversion: gravity in the camera frame from the ground truth agrees with
    # what the accelerometer measures (rotated into the camera frame) while the MAV rests.
    acc_b = np.concatenate([f.imu.acc_mps2 for f in frames]).mean(axis=0)
    assert stereo.T_b_c is not None
    acc_c = stereo.T_b_c[:3, :3].T @ acc_b
    g_c = f0.T_w_c_gt[:3, :3].T @ np.array([0.0, 0.0, 9.81])
    assert np.degrees(np.arccos(acc_c @ g_c / np.linalg.norm(acc_c) / np.linalg.norm(g_c))) < 2.0


def test_camera_frame_ground_truth_option(root: Path, tmp_path: Path) -> None:
    gt = root / "extra/V101_gt_evo_tum_format.txt"
    ds = EurocDataset(root=root, groundtruth=str(gt), groundtruth_frame="camera", imu=False)
    assert ds.ground_truth is not None
    np.testing.assert_allclose(ds.ground_truth.positions_m[0], [0.878895, 2.183400, 0.948427])
    assert ds[0].imu.t_s.size == 0


def test_rectified_stereo_from_orbslam_settings(root: Path, shared_datasets: Path) -> None:
    settings = shared_datasets / "calib/orb_slam2_examples/Stereo_EuRoC.yaml"
    ds = EurocDataset(root=root, stereo=True, settings=str(settings), imu=False)
    assert ds.camera.K[0, 0] == pytest.approx(435.2046959714599)
    assert ds.T_l_r is not None
    np.testing.assert_allclose(ds.T_l_r[:3, :3], np.eye(3))
    assert ds.T_l_r[0, 3] == pytest.approx(47.90639384423901 / 435.2046959714599)
    uv_l, uv_r = _stereo_matches(ds, 20)
    dy = uv_l[:, 1] - uv_r[:, 1]
    # Rectified: corresponding points share a row, and disparities are positive.
    assert np.median(np.abs(dy)) < 0.5
    assert np.percentile(np.abs(dy), 90) < 1.5
    assert np.median(uv_l[:, 0] - uv_r[:, 0]) > 0
    mono = EurocDataset(root=root, settings=str(settings), imu=False)
    np.testing.assert_array_equal(mono[20].image, ds[20].image)  # a monocular run is rectified too
    assert mono.T_l_r is None and mono.camera_right is None
    assert mono.T_b_c is not None and ds.T_b_c is not None
    np.testing.assert_allclose(mono.T_b_c, ds.T_b_c)
    # The rectified left camera is rotated by LEFT.R from the raw cam0: T_b_c follows.
    R_l = np.array(
        [
            [0.999966347530033, -0.001422739138722922, 0.008079580483432283],
            [0.001365741834644127, 0.9999741760894847, 0.007055629199258132],
            [-0.008089410156878961, -0.007044357138835809, 0.9999424675829176],
        ]
    )
    np.testing.assert_allclose(ds.T_b_c[:3, :3], T_BS_CAM0[:3, :3] @ R_l.T, atol=1e-12)
    raw_l, raw_r = _stereo_matches(EurocDataset(root=root, stereo=True, imu=False), 20)
    assert np.median(np.abs(raw_l[:, 1] - raw_r[:, 1])) > 5.0  # the raw pair is not row-aligned


def _stereo_matches(ds: EurocDataset, i: int) -> tuple[np.ndarray, np.ndarray]:
    """ORB matches of frame i's left/right images, RANSAC-fundamental inliers: (M, 2) px each."""
    f = ds[i]
    assert f.image_right is not None
    orb = cv2.ORB.create(1000)
    kl, dl = orb.detectAndCompute(f.image, None)
    kr, dr = orb.detectAndCompute(f.image_right, None)
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(dl, dr)
    uv_l = np.array([kl[m.queryIdx].pt for m in matches], dtype=np.float64)
    uv_r = np.array([kr[m.trainIdx].pt for m in matches], dtype=np.float64)
    _, mask = cv2.findFundamentalMat(uv_l, uv_r, cv2.FM_RANSAC, 1.0, 0.999)
    inl = mask.ravel() == 1
    assert inl.sum() > 100
    return uv_l[inl], uv_r[inl]


def test_raw_stereo_extrinsics_satisfy_epipolar_constraint(stereo: EurocDataset) -> None:
    uv_l, uv_r = _stereo_matches(stereo, 20)
    assert stereo.T_l_r is not None and stereo.camera_right is not None
    b_l = stereo.camera.unproject(uv_l)
    b_r = stereo.camera_right.unproject(uv_r)

    def residual_deg(T_r_l: np.ndarray) -> float:
        t = T_r_l[:3, 3]
        E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ T_r_l[:3, :3]
        n = b_l @ E.T  # epipolar plane normals in the right camera
        s = np.abs(np.sum(b_r * n, axis=1)) / np.linalg.norm(n, axis=1)
        return float(np.degrees(np.median(np.arcsin(np.clip(s, 0, 1)))))

    # T_l_r maps right-camera points to the left camera, so T_r_l = inv(T_l_r) gives x_r^T E x_l = 0.
    good = residual_deg(np.linalg.inv(stereo.T_l_r))
    assert good < 0.1  # ~0.4 px at fx = 458 px
    assert residual_deg(stereo.T_l_r) > 3 * good


def test_missing_and_broken_files(root: Path, tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match=r"mav0/: folder .*/mav0 does not exist"):
        EurocDataset(root=tmp_path)
    seq = _copy_mav0(root, tmp_path / "seq")
    EurocDataset(root=seq)  # the copy is sound
    (seq / "mav0/cam0/sensor.yaml").unlink()
    with pytest.raises(CalibrationError, match=r"cam0/sensor\.yaml does not exist"):
        EurocDataset(root=seq)


@pytest.mark.parametrize(
    ("file", "line_no", "new_line", "pattern"),
    [
        ("mav0/imu0/data.csv", 3, "1403715273267142912,0.1,0.2", r"imu0/data\.csv:3: expected 7 columns"),
        (
            "mav0/imu0/data.csv",
            3,
            "1403715273267142912,0.1,0.2,0.3,abc,1,2",
            r"imu0/data\.csv:3: column 5 should be a number",
        ),
        (
            "mav0/imu0/data.csv",
            4,
            "1403715273262142976,0,0,0,0,0,0",
            r"imu0/data\.csv:4: IMU timestamps must be strictly",
        ),
        (
            "mav0/cam0/data.csv",
            3,
            "1403715273.31,1403715273312143104.png",
            r"cam0/data\.csv:3: column 1 should be an integer",
        ),
        (
            "mav0/cam0/data.csv",
            3,
            "1403715273362142976,1403715273312143104.png",
            r"cam0/data\.csv:4: .*strictly increasing",
        ),
    ],
)
def test_malformed_csv(root: Path, tmp_path: Path, file: str, line_no: int, new_line: str, pattern: str) -> None:
    seq = _copy_mav0(root, tmp_path / "seq")
    lines = (seq / file).read_text().splitlines()
    lines[line_no - 1] = new_line
    (seq / file).write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=pattern):
        EurocDataset(root=seq)


def test_resolution_disagreeing_with_images(root: Path, tmp_path: Path) -> None:
    seq = _copy_mav0(root, tmp_path / "seq")
    yaml = seq / "mav0/cam0/sensor.yaml"
    yaml.write_text(yaml.read_text().replace("resolution: [752, 480]", "resolution: [640, 480]"))
    ds = EurocDataset(root=seq)
    with pytest.raises(
        CalibrationError,
        match=r"1403715273262142976\.png is 752x480 px but the calibration \(.*cam0/sensor\.yaml\) is 640x480",
    ):
        ds[0]


def test_malformed_sensor_yaml(root: Path, tmp_path: Path) -> None:
    seq = _copy_mav0(root, tmp_path / "seq")
    yaml = seq / "mav0/cam0/sensor.yaml"
    yaml.write_text(
        yaml.read_text().replace("intrinsics: [458.654, 457.296, 367.215, 248.375]", "intrinsics: [458.654, 457.296]")
    )
    with pytest.raises(CalibrationError, match=r"cam0/sensor\.yaml: 'intrinsics' has 2 numbers; expected 4"):
        EurocDataset(root=seq)


def test_stereo_settings_without_a_baseline_are_refused_naming_the_file(root: Path, shared_datasets: Path) -> None:
    """Issue 16 (bad input): EuRoC stereo with an ORB-SLAM settings file that has neither LEFT/RIGHT rectification
    blocks nor Camera.bf / Stereo.b (the monocular EuRoC file): refused before the first frame, naming the file."""
    mono = shared_datasets / "calib/orb_slam2_examples/Monocular_EuRoC.yaml"
    with pytest.raises(CalibrationError, match=r"Monocular_EuRoC\.yaml: stereo needs Camera\.bf \(or Stereo\.b\)"):
        EurocDataset(root=root, stereo=True, settings=str(mono))
