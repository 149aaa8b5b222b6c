"""Fixtures for the tests of ORB-SLAM's extractor (plugin slamkit_orb): extractors and real images."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray
from slamkit_orb.orbslam_extractor import OrbSlamExtractor


@pytest.fixture(scope="module")
def extractor() -> OrbSlamExtractor:
    """ORB-SLAM's defaults: 1000 features, 8 levels of 1.2, FAST 20/7, 30 px cells."""
    return OrbSlamExtractor()


def _read_grey(path: Path) -> NDArray[np.uint8]:
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    assert image is not None, f"could not read {path}"
    return np.asarray(image, np.uint8)


@pytest.fixture(scope="session")
def tum_image(shared_datasets: Path) -> NDArray[np.uint8]:
    """First frame of TUM RGB-D fr1/xyz, 640x480, as grey."""
    rgb = shared_datasets / "tum_rgbd" / "rgbd_dataset_freiburg1_xyz_first10" / "rgb"
    return _read_grey(sorted(rgb.glob("*.png"))[0])


@pytest.fixture(scope="session")
def euroc_image(shared_datasets: Path) -> NDArray[np.uint8]:
    """First cam0 frame of EuRoC V1_01_easy, 752x480 grey (strong radial-tangential distortion)."""
    data = shared_datasets / "euroc" / "V1_01_easy" / "mav0" / "cam0" / "data"
    return _read_grey(sorted(data.glob("*.png"))[0])


@pytest.fixture(scope="session")
def kitti_image(shared_datasets: Path) -> NDArray[np.uint8]:
    """First left frame of KITTI odometry 07, 1241x376 grey."""
    return _read_grey(shared_datasets / "kitti" / "sequences" / "07" / "image_0" / "000000.png")
