"""Folder and video readers on real TUM images (copied / encoded into tmp_path)."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from slamkit.errors import CalibrationError, ConfigError, DatasetError
from slamkit.geometry.camera import KannalaBrandtCamera
from slamkit.interfaces import Dataset
from slamkit.io.folder import FolderDataset
from slamkit.io.video import VideoDataset

FR1_RGB = "tum_rgbd/rgbd_dataset_freiburg1_xyz_first10/rgb"
CAMERA = {"fx": 517.3, "fy": 516.5, "cx": 318.6, "cy": 255.3, "dist": [0.2624, -0.9531, -0.0054, 0.0026, 1.1633]}


@pytest.fixture(scope="module")
def rgb(shared_datasets: Path) -> Path:
    return shared_datasets / FR1_RGB


def _copy_images(src: Path, dst: Path) -> Path:
    dst.mkdir()
    for f in sorted(src.glob("*.png")):
        shutil.copyfile(f, dst / f.name)
    return dst


def test_folder_with_fps(rgb: Path) -> None:
    ds = FolderDataset(root=rgb, fps=30.0, camera=CAMERA)
    assert isinstance(ds, Dataset)
    assert len(ds) == 10
    np.testing.assert_allclose(ds.timestamps()[:3], [0.0, 1 / 30, 2 / 30])
    assert (ds.camera.width, ds.camera.height) == (640, 480)
    assert ds.camera.K[0, 0] == 517.3
    f = ds[0]
    assert f.color is not None and f.image.shape == (480, 640)
    np.testing.assert_array_equal(f.color, np.asarray(cv2.imread(str(rgb / "1305031102.175304.png"))))
    assert f.source.endswith("1305031102.175304.png") and f.depth_m is None and f.T_w_c_gt is None


def test_folder_times_from_names(rgb: Path) -> None:
    ds = FolderDataset(root=rgb, timestamps_from_names=True, camera=CAMERA)
    assert ds.timestamps()[0] == 1305031102.175304
    assert ds.fps == pytest.approx(1 / 0.0320, rel=0.05)  # median step of the names, ~31 Hz


def test_folder_camera_from_settings(rgb: Path, shared_datasets: Path) -> None:
    settings = shared_datasets / "calib/orb_slam2_examples/Monocular_TUM1.yaml"
    ds = FolderDataset(root=rgb, fps=30, settings=str(settings))
    assert ds.camera.K[0, 0] == 517.306408 and ds.camera.width == 640
    fisheye = {"model": "kannala_brandt", "fx": 300.0, "fy": 300.0, "cx": 320.0, "cy": 240.0, "k": [0.0, 0.0, 0.0, 0.0]}
    assert isinstance(FolderDataset(root=rgb, fps=30, camera=fisheye).camera, KannalaBrandtCamera)


def test_folder_config_errors(rgb: Path, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"dataset\.fps is required"):
        FolderDataset(root=rgb, camera=CAMERA)
    with pytest.raises(ConfigError, match=r"dataset\.camera .* or dataset\.settings .* is required"):
        FolderDataset(root=rgb, fps=30)
    with pytest.raises(ConfigError, match=r"dataset\.camera\.fx: expected a positive number"):
        FolderDataset(root=rgb, fps=30, camera={**CAMERA, "fx": -1.0})
    with pytest.raises(DatasetError, match=r"folder .*nowhere does not exist"):
        FolderDataset(root=tmp_path / "nowhere", fps=30, camera=CAMERA)
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match=r"empty holds no image files"):
        FolderDataset(root=tmp_path / "empty", fps=30, camera=CAMERA)


def test_folder_bad_images(rgb: Path, tmp_path: Path) -> None:
    root = _copy_images(rgb, tmp_path / "imgs")
    (root / "1305031102.211214.png").write_bytes((root / "1305031102.211214.png").read_bytes()[:500])
    cv2.imwrite(str(root / "1305031102.243211.png"), np.zeros((480, 600, 3), np.uint8))
    ds = FolderDataset(root=root, fps=30, camera=CAMERA)
    with pytest.raises(DatasetError, match=r"1305031102\.211214\.png could not be decoded"):
        ds[1]
    with pytest.raises(
        CalibrationError,
        match=r"1305031102\.243211\.png is 600x480 px but the calibration \(config dataset\.camera\) is 640x480",
    ):
        ds[2]
    (root / "frame.png").write_bytes((root / "1305031102.175304.png").read_bytes())
    with pytest.raises(DatasetError, match=r"frame\.png: .*file name should be a number"):
        FolderDataset(root=root, timestamps_from_names=True, camera=CAMERA)


@pytest.fixture
def video(rgb: Path, tmp_path: Path) -> Path:
    path = tmp_path / "fr1.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 15.0, (640, 480))
    assert writer.isOpened()
    for f in sorted(rgb.glob("*.png")):
        writer.write(np.asarray(cv2.imread(str(f))))
    writer.release()
    return path


def test_video_frames_and_random_access(video: Path, rgb: Path) -> None:
    ds = VideoDataset(root=video, camera=CAMERA)
    assert isinstance(ds, Dataset)
    assert len(ds) == 10 and ds.fps == 15.0
    frames = list(ds)
    assert frames[4].timestamp_s == pytest.approx(4 / 15)
    assert frames[0].color is not None and frames[0].image.shape == (480, 640)
    originals = [np.asarray(cv2.imread(str(f)), dtype=np.int16) for f in sorted(rgb.glob("*.png"))]
    # MJPEG is lossy, but each frame is far closer to its own source image than to its neighbour.
    for k in (2, 7):
        own = np.abs(ds[k].color.astype(np.int16) - originals[k]).mean()  # type: ignore[union-attr]
        other = np.abs(ds[k].color.astype(np.int16) - originals[k + 1]).mean()  # type: ignore[union-attr]
        assert own < 6 and own < other / 3
    np.testing.assert_array_equal(ds[3].image, frames[3].image)  # going back reopens the file
    ds.close()
    assert len(VideoDataset(root=video, fps=30.0, camera=CAMERA, max_frames=4)) == 4


def test_video_errors(video: Path, tmp_path: Path) -> None:
    bad = tmp_path / "bad.avi"
    bad.write_bytes(b"\x00" * 4096)
    with pytest.raises(DatasetError, match=r"bad\.avi could not be opened|bad\.avi has no decodable frame"):
        VideoDataset(root=bad, camera=CAMERA)
    with pytest.raises(DatasetError, match=r"video \(dataset\.root\): file .*missing\.mp4 does not exist"):
        VideoDataset(root=tmp_path / "missing.mp4", camera=CAMERA)
    ds = VideoDataset(root=video, camera={**CAMERA, "width": 320, "height": 240})
    with pytest.raises(CalibrationError, match=r"fr1\.avi#frame0 is 640x480 px but the calibration"):
        ds[0]
