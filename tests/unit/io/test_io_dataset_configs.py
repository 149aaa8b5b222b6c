"""conf/dataset/{tum_rgbd,euroc,kitti,folder,video}.yaml: keys match the readers and Hydra builds them."""

from __future__ import annotations

import inspect
from pathlib import Path

import cv2
import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import get_class, instantiate
from omegaconf import OmegaConf

from slamkit.interfaces import Dataset
from slamkit.io.base import SequenceDataset

CONF = Path(__file__).resolve().parents[3] / "conf"
NODES = ("tum_rgbd", "euroc", "kitti", "folder", "video")


@pytest.mark.parametrize("name", NODES)
def test_node_keys_are_the_constructor_keywords(name: str) -> None:
    path = CONF / "dataset" / f"{name}.yaml"
    cfg = OmegaConf.load(path)
    cls = get_class(cfg._target_)
    params = list(inspect.signature(cls).parameters)
    keys = [str(k) for k in cfg if k != "_target_"]
    assert sorted(keys) == sorted(params)
    assert OmegaConf.is_missing(cfg, "root")
    assert cfg.skip is None and cfg.max_frames is None
    # Every option is commented on its line.
    for line in path.read_text().splitlines():
        if line and not line.startswith("#") and not line.startswith("_target_"):
            assert "#" in line, f"{path.name}: option without a comment: {line}"


def _build(name: str, overrides: list[str]) -> SequenceDataset:
    with initialize_config_dir(config_dir=str(CONF / "dataset"), version_base="1.3"):
        cfg = compose(config_name=name, overrides=overrides)
    ds = instantiate(cfg)
    assert isinstance(ds, Dataset) and isinstance(ds, SequenceDataset)
    return ds


def test_hydra_builds_each_reader(shared_datasets: Path, tmp_path: Path) -> None:
    d = shared_datasets
    tum = _build("tum_rgbd", [f"root={d}/tum_rgbd/rgbd_dataset_freiburg1_xyz_first10", "max_frames=3", "use_depth=true"])
    assert len(tum) == 3 and tum[0].depth_m is not None
    # use_depth: null (the node's default, resolved by the app from the front end) builds without depth
    assert _build("tum_rgbd", [f"root={d}/tum_rgbd/rgbd_dataset_freiburg1_xyz_first10"])[0].depth_m is None
    euroc = _build(
        "euroc",
        [
            f"root={d}/euroc/V1_01_easy",
            "stereo=true",
            f"groundtruth={d}/euroc/V1_01_easy/extra/V101_gt_evo_tum_format.txt",
            "skip=[1,89]",
        ],
    )
    assert len(euroc) == 6 and euroc[0].image_right is not None and euroc[0].T_w_c_gt is not None
    # After the skipped span the IMU covers the whole gap: (frame 0 time, frame 90 time] ~ 900 samples.
    assert len(euroc[1].imu) == 900
    kitti = _build("kitti", [f"root={d}/kitti", "sequence='07'"])
    assert len(kitti) == 160
    cam = "camera={fx: 517.3, fy: 516.5, cx: 318.6, cy: 255.3, dist: [0.2624, -0.9531, -0.0054, 0.0026, 1.1633]}"
    folder = _build("folder", [f"root={d}/tum_rgbd/rgbd_dataset_freiburg1_xyz_first10/rgb", "fps=30", cam])
    assert len(folder) == 10 and folder.camera.K[0, 0] == 517.3
    video = tmp_path / "v.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter.fourcc(*"MJPG"), 10.0, (640, 480))
    for f in sorted((d / "tum_rgbd/rgbd_dataset_freiburg1_xyz_first10/rgb").glob("*.png"))[:3]:
        writer.write(np.asarray(cv2.imread(str(f))))
    writer.release()
    settings = d / "calib/orb_slam2_examples/Monocular_TUM1.yaml"
    vid = _build("video", [f"root={video}", f"settings={settings}"])
    assert len(vid) == 3 and vid.camera.K[0, 0] == 517.306408
