"""TUM RGB-D reader on the shared fr1_xyz (first 10 frames) and fr3 (4 frames) folders, and broken copies."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slamkit.errors import CalibrationError, ConfigError, DatasetError
from slamkit.geometry.camera import PinholeCamera
from slamkit.interfaces import Dataset
from slamkit.io.tum_rgbd import TumRgbdDataset

FR1 = "tum_rgbd/rgbd_dataset_freiburg1_xyz_first10"
FR3 = "tum_rgbd/rgbd_dataset_freiburg3_long_office_household_4frames"


@pytest.fixture
def fr1(shared_datasets: Path) -> Path:
    return shared_datasets / FR1


def _copy_seq(src: Path, dst: Path) -> Path:
    """Writable copy of a TUM folder: text files copied, image folders copied too (they are small)."""
    shutil.copytree(src, dst)
    for p in dst.rglob("*"):
        p.chmod(0o755 if p.is_dir() else 0o644)
    dst.chmod(0o755)
    return dst


def test_fr1_frames_depth_intrinsics(fr1: Path) -> None:
    ds = TumRgbdDataset(root=fr1)
    assert isinstance(ds, Dataset)
    # associate.py pairs 9 of the 10 colour frames (1305031102.243211 loses its depth partner).
    assert len(ds) == 9
    t = ds.timestamps()
    assert t[0] == 1305031102.175304
    assert 1305031102.243211 not in t
    cam = ds.camera
    assert (cam.width, cam.height) == (640, 480)
    np.testing.assert_allclose(cam.K, [[517.3, 0.0, 318.6], [0.0, 516.5, 255.3], [0.0, 0.0, 1.0]])
    assert isinstance(cam, PinholeCamera)
    np.testing.assert_allclose(cam.dist, np.array([0.2624, -0.9531, -0.0054, 0.0026, 1.1633]))
    f = ds[0]
    assert f.image.shape == (480, 640) and f.image.dtype == np.uint8
    assert f.color is not None and f.color.shape == (480, 640, 3)
    assert f.source.endswith("rgb/1305031102.175304.png")
    raw = np.asarray(cv2.imread(str(fr1 / "depth/1305031102.160407.png"), cv2.IMREAD_UNCHANGED))
    assert f.depth_m is not None and f.depth_m.dtype == np.float32
    np.testing.assert_allclose(f.depth_m, raw.astype(np.float32) / 5000.0)
    valid = f.depth_m[f.depth_m > 0]
    assert 0.3 < np.median(valid) < 3.0  # a desk scene seen by a Kinect


def test_fr1_ground_truth_interpolated_at_frame_time(fr1: Path) -> None:
    ds = TumRgbdDataset(root=fr1)
    assert ds.ground_truth is not None and len(ds.ground_truth) > 0
    gt = np.loadtxt(fr1 / "groundtruth.txt")
    t = 1305031102.175304
    j = int(np.searchsorted(gt[:, 0], t))
    a = (t - gt[j - 1, 0]) / (gt[j, 0] - gt[j - 1, 0])
    f = ds[0]
    assert f.T_w_c_gt is not None
    np.testing.assert_allclose(f.T_w_c_gt[:3, 3], (1 - a) * gt[j - 1, 1:4] + a * gt[j, 1:4], atol=1e-9)
    R_prev = Rotation.from_quat(gt[j - 1, 4:8])
    ang = (R_prev.inv() * Rotation.from_matrix(f.T_w_c_gt[:3, :3])).magnitude()
    assert ang < np.deg2rad(0.5)
    assert all(fr.T_w_c_gt is not None for fr in ds)


def test_fr3_folder_without_lists_uses_image_names(shared_datasets: Path) -> None:
    gt = shared_datasets / "tum_rgbd/gt_only/rgbd_dataset_freiburg3_long_office_household/groundtruth.txt"
    ds = TumRgbdDataset(root=shared_datasets / FR3, groundtruth=str(gt))
    assert len(ds) == 4
    np.testing.assert_allclose(
        ds.timestamps(), [1341847980.722988, 1341847984.106759, 1341847987.458620, 1341847990.710795]
    )
    np.testing.assert_allclose(ds.camera.K[0, 0], 535.4)
    frames = list(ds)
    assert all(f.depth_m is None for f in frames)
    # The ground truth starts at 1341847980.79, after the first image: no pose for frame 0.
    assert frames[0].T_w_c_gt is None
    assert all(f.T_w_c_gt is not None for f in frames[1:])


def test_gt_only_folder_names_the_missing_image(shared_datasets: Path) -> None:
    root = shared_datasets / "tum_rgbd/gt_only/rgbd_dataset_freiburg1_xyz"
    with pytest.raises(
        DatasetError, match=r"rgb\.txt:4: image file .*rgb/1305031102\.175304\.png listed there does not exist"
    ):
        TumRgbdDataset(root=root)


def test_skip_and_max_frames(fr1: Path) -> None:
    ds = TumRgbdDataset(root=fr1, skip=[1, 3], max_frames=4)
    full = TumRgbdDataset(root=fr1).timestamps()
    np.testing.assert_array_equal(ds.timestamps(), full[[0, 4, 5, 6]])
    assert [f.index for f in ds] == [0, 1, 2, 3]


def test_settings_replace_intrinsics_and_depth_factor(fr1: Path, shared_datasets: Path) -> None:
    settings = shared_datasets / "calib/orb_slam2_examples/RGB-D_TUM2.yaml"
    ds = TumRgbdDataset(root=fr1, settings=str(settings))
    assert ds.camera.K[0, 0] == 520.908620
    assert ds.depth_scale == 5208.0
    assert TumRgbdDataset(root=fr1, settings=str(settings), depth_scale=5000).depth_scale == 5000.0


def test_unknown_sensor_needs_intrinsics(fr1: Path, tmp_path: Path) -> None:
    root = _copy_seq(fr1, tmp_path / "my_sequence")
    with pytest.raises(CalibrationError, match=r"my_sequence: cannot tell the TUM sensor"):
        TumRgbdDataset(root=root)
    assert TumRgbdDataset(root=root, intrinsics="fr3").camera.K[0, 0] == 535.4
    with pytest.raises(ConfigError, match=r"dataset\.intrinsics"):
        TumRgbdDataset(root=root, intrinsics="fr9")


def test_missing_root() -> None:
    with pytest.raises(DatasetError, match=r"folder /no/such/freiburg1_seq does not exist"):
        TumRgbdDataset(root="/no/such/freiburg1_seq")


@pytest.mark.parametrize(
    ("file", "line_no", "new_line", "pattern"),
    [
        ("rgb.txt", 5, "1305031102.211214", r"rgb\.txt:5: expected 2 columns"),
        ("rgb.txt", 5, "13050311O2.211214 rgb/1305031102.211214.png", r"rgb\.txt:5: column 1 should be a number"),
        ("rgb.txt", 5, "1305031102.100000 rgb/1305031102.211214.png", r"rgb\.txt:5: .*strictly increasing"),
        ("depth.txt", 6, "1305031102.0 depth/1305031102.226738.png", r"depth\.txt:6: .*strictly increasing"),
        ("groundtruth.txt", 4, "1305031098.6659 1.3563 0.6305", r"groundtruth\.txt:4: expected 8 columns"),
    ],
)
def test_malformed_lists(fr1: Path, tmp_path: Path, file: str, line_no: int, new_line: str, pattern: str) -> None:
    root = _copy_seq(fr1, tmp_path / "rgbd_dataset_freiburg1_xyz")
    lines = (root / file).read_text().splitlines()
    lines[line_no - 1] = new_line
    (root / file).write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=pattern):
        TumRgbdDataset(root=root)


def test_truncated_and_wrong_size_images(fr1: Path, tmp_path: Path) -> None:
    root = _copy_seq(fr1, tmp_path / "rgbd_dataset_freiburg1_xyz")
    img = root / "rgb/1305031102.211214.png"
    img.write_bytes(img.read_bytes()[:1000])
    ds = TumRgbdDataset(root=root)
    ds[0]
    with pytest.raises(DatasetError, match=r"rgb/1305031102\.211214\.png could not be decoded"):
        ds[1]
    small = root / "rgb/1305031102.275326.png"
    cv2.imwrite(str(small), np.zeros((240, 320, 3), np.uint8))
    with pytest.raises(CalibrationError, match=r"1305031102\.275326\.png is 320x240 px but the calibration \(TUM fr1"):
        ds[2]
    depth = root / "depth/1305031102.295279.png"
    cv2.imwrite(str(depth), np.zeros((480, 641), np.uint16))
    with pytest.raises(CalibrationError, match=r"depth/1305031102\.295279\.png is 641x480 px"):
        ds[3]


def test_no_depth_list_falls_back_to_folder_then_to_none(fr1: Path, tmp_path: Path) -> None:
    root = _copy_seq(fr1, tmp_path / "rgbd_dataset_freiburg1_xyz")
    (root / "depth.txt").unlink()
    (root / "rgb.txt").unlink()
    ds = TumRgbdDataset(root=root)
    assert len(ds) == 9 and ds[0].depth_m is not None  # same association from the file names
    shutil.rmtree(root / "depth")
    ds = TumRgbdDataset(root=root)
    assert len(ds) == 10 and ds[0].depth_m is None
    assert len(TumRgbdDataset(root=fr1, use_depth=False)) == 10
