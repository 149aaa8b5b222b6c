"""KITTI reader on the shared sequence 07 (first 160 images of 1101, calib, times, poses)."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from slamkit.errors import CalibrationError, DatasetError
from slamkit.interfaces import Dataset
from slamkit.io.kitti import KittiDataset


@pytest.fixture(scope="module")
def kitti(shared_datasets: Path) -> Path:
    return shared_datasets / "kitti"


def _copy_seq07(src: Path, dst: Path, n_images: int = 5, stereo: bool = False) -> Path:
    """Writable KITTI root with sequence 07 trimmed to n images (image_1 = copies of image_0 if stereo)."""
    seq = dst / "sequences/07"
    (seq / "image_0").mkdir(parents=True)
    for name in ("calib.txt", "times.txt"):
        shutil.copyfile(src / "sequences/07" / name, seq / name)
    (dst / "poses").mkdir()
    shutil.copyfile(src / "poses/07.txt", dst / "poses/07.txt")
    for k in range(n_images):
        shutil.copyfile(src / f"sequences/07/image_0/{k:06d}.png", seq / f"image_0/{k:06d}.png")
    if stereo:
        shutil.copytree(seq / "image_0", seq / "image_1")
    return dst


def test_sequence_07(kitti: Path) -> None:
    ds = KittiDataset(root=kitti, sequence="07")
    assert isinstance(ds, Dataset)
    assert len(ds) == 160  # the images present; times.txt has 1101 lines
    assert ds.timestamps()[0] == 0.0
    assert ds.timestamps()[1] == pytest.approx(0.1038752)
    np.testing.assert_allclose(ds.camera.K, [[707.0912, 0.0, 601.8873], [0.0, 707.0912, 183.1104], [0.0, 0.0, 1.0]])
    assert (ds.camera.width, ds.camera.height) == (1226, 370)
    f = ds[5]
    assert f.image.shape == (370, 1226) and f.image_right is None
    assert f.source.endswith("image_0/000005.png")
    assert ds.ground_truth is not None and len(ds.ground_truth) == 1101
    line6 = np.array((kitti / "poses/07.txt").read_text().splitlines()[5].split(), dtype=float).reshape(3, 4)
    assert f.T_w_c_gt is not None
    np.testing.assert_array_equal(f.T_w_c_gt[:3], line6)
    np.testing.assert_array_equal(f.T_w_c_gt[3], [0, 0, 0, 1])
    # Baseline from P1: 379.8145 / 707.0912 m (KITTI's ~0.54 m stereo rig).
    assert ds.baseline_m == pytest.approx(379.8145 / 707.0912)
    assert len(KittiDataset(root=kitti, sequence=7, max_frames=3, skip=[0, 9])) == 3


def test_stereo_right_images(kitti: Path, tmp_path: Path) -> None:
    root = _copy_seq07(kitti, tmp_path, n_images=3, stereo=True)
    right = root / "sequences/07/image_1/000001.png"
    cv2.imwrite(str(right), np.full((370, 1226), 77, np.uint8))
    ds = KittiDataset(root=root, sequence="07", stereo=True)
    assert ds.T_l_r is not None and ds.camera_right is ds.camera
    np.testing.assert_allclose(ds.T_l_r[:3, 3], [0.5371506, 0, 0], atol=1e-6)
    f = ds[1]
    assert f.image_right is not None and np.all(f.image_right == 77)
    (root / "sequences/07/image_1/000002.png").unlink()
    with pytest.raises(DatasetError, match=r"image_1: right image 000002\.png .*does not exist"):
        KittiDataset(root=root, sequence="07", stereo=True)
    with pytest.raises(
        DatasetError, match=r"KITTI sequence 07 right images \(stereo\): folder .*image_1 does not exist"
    ):
        KittiDataset(root=kitti, sequence="07", stereo=True)


def test_orbslam_settings_with_other_image_size(kitti: Path, shared_datasets: Path) -> None:
    mono = shared_datasets / "calib/orb_slam2_examples/Monocular_KITTI04-12.yaml"
    ds = KittiDataset(root=kitti, settings=str(mono))
    assert ds.camera.K[0, 0] == 707.0912 and ds.fps == 10.0
    assert ds[0].image.shape == (370, 1226)  # size taken from the images (the file has none)
    stereo = shared_datasets / "calib/orb_slam2_examples/Stereo_KITTI04-12.yaml"
    ds = KittiDataset(root=kitti, settings=str(stereo))
    # ORB-SLAM2's KITTI04-12 file says 1241x376, but sequence 07's images are 1226x370.
    with pytest.raises(
        CalibrationError,
        match=r"000000\.png is 1226x370 px but the calibration \(.*Stereo_KITTI04-12\.yaml\) is 1241x376",
    ):
        ds[0]


@pytest.mark.parametrize(
    ("file", "line_no", "new_line", "pattern"),
    [
        ("sequences/07/calib.txt", 2, "P1: 7.07e+02 0 6.01e+02", r"calib\.txt:2: expected 13 columns"),
        (
            "sequences/07/calib.txt",
            1,
            "P0: 7.07e+02 0 6.01e+02 0 0 7.07e+02 1.83e+02 0 0 0 one 0",
            r"calib\.txt:1: column 12 should be a number",
        ),
        ("sequences/07/times.txt", 3, "0.05", r"times\.txt:3: KITTI times must be strictly increasing"),
        ("sequences/07/times.txt", 2, "0.1 0.2", r"times\.txt:2: expected 1 columns"),
        ("poses/07.txt", 2, "1 0 0 0 0 1 0 0 0 0 1", r"07\.txt:2: expected 12 columns"),
    ],
)
def test_malformed_text_files(
    kitti: Path, tmp_path: Path, file: str, line_no: int, new_line: str, pattern: str
) -> None:
    root = _copy_seq07(kitti, tmp_path)
    lines = (root / file).read_text().splitlines()
    lines[line_no - 1] = new_line
    (root / file).write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=pattern):
        KittiDataset(root=root, sequence="07")


def test_missing_calib_line_image_gap_and_bad_image(kitti: Path, tmp_path: Path) -> None:
    root = _copy_seq07(kitti, tmp_path)
    seq = root / "sequences/07"
    calib = (seq / "calib.txt").read_text().splitlines()
    (seq / "calib.txt").write_text("\n".join([calib[0], *calib[2:]]) + "\n")
    with pytest.raises(CalibrationError, match=r"calib\.txt: missing the 'P1:' line"):
        KittiDataset(root=root, sequence="07")
    (seq / "calib.txt").write_text("\n".join(calib) + "\n")
    (seq / "image_0/000003.png").write_bytes(b"not a png")
    ds = KittiDataset(root=root, sequence="07")
    with pytest.raises(DatasetError, match=r"image_0/000003\.png could not be decoded"):
        ds[3]
    (seq / "image_0/000002.png").unlink()
    with pytest.raises(
        DatasetError, match=r"expected image 000002\.png \(consecutive frame numbers\), found 000003\.png"
    ):
        KittiDataset(root=root, sequence="07")
    with pytest.raises(DatasetError, match=r"KITTI sequence 99: folder .*sequences/99 does not exist"):
        KittiDataset(root=root, sequence="99")


def test_stereo_settings_without_a_baseline_are_refused_naming_the_file(kitti: Path, shared_datasets: Path) -> None:
    """Issue 16 (bad input): a stereo run given an ORB-SLAM settings file with no Camera.bf / Stereo.b (here the
    monocular KITTI file) stops before the first frame, the message naming the file and the missing key."""
    mono = shared_datasets / "calib/orb_slam2_examples/Monocular_KITTI04-12.yaml"
    with pytest.raises(CalibrationError, match=r"Monocular_KITTI04-12\.yaml: stereo needs Camera\.bf \(or Stereo\.b\)"):
        KittiDataset(root=kitti, sequence="01", stereo=True, settings=str(mono))
