"""dataset=rosbag (issue 18.4): ROS 1, ROS 2 (sqlite3) and MCAP bags written from the synthetic room with rosbags'
own writers read back as the room's frames (images bit for bit: PNG is lossless; IMU samples; calibration from
camera_info); bad bags give errors naming the bag and the topic. The trajectory through a whole run:
tests/integration/test_rosbag_room.py."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from rosbag_room import DEPTH_TOPIC, IMAGE_TOPIC, IMU_TOPIC, INFO_TOPIC, RAW_TOPIC, room, write_room_bag

from slamkit.app import build_components
from slamkit.config import compose_config
from slamkit.errors import CalibrationError, DatasetError
from slamkit.io.rosbag import RosbagDataset
from slamkit.plugins import ComponentRegistry

pytest.importorskip("rosbags", reason="rosbags reads and writes the bags")

N = 4


@pytest.fixture(scope="module")
def frames() -> tuple[list, object]:
    ds = room(N)
    return list(ds), ds.camera


def bag_path(tmp_path: Path, kind: str) -> Path:
    return tmp_path / ("room.bag" if kind == "ros1" else f"room_{kind}")


@pytest.mark.parametrize("kind", ["ros1", "ros2", "mcap"])
def test_a_bag_of_the_room_reads_back_as_the_room(tmp_path: Path, frames: tuple[list, object], kind: str) -> None:
    src, camera = frames
    path = write_room_bag(bag_path(tmp_path, kind), src, camera, kind)
    bag = RosbagDataset(path, IMAGE_TOPIC, imu_topic=IMU_TOPIC, camera_info_topic=INFO_TOPIC)
    assert len(bag) == N and bag.fps == 30.0
    assert repr(bag.camera) == repr(camera)
    got = list(bag)
    for a, b in zip(src, got, strict=True):
        assert b.index == a.index and abs(b.timestamp_s - a.timestamp_s) < 1e-9
        assert np.array_equal(b.image, a.image) and b.color is None
        assert np.allclose(b.imu.t_s, a.imu.t_s, rtol=0, atol=1e-9)
        assert np.array_equal(b.imu.acc_mps2, a.imu.acc_mps2) and np.array_equal(b.imu.gyro_radps, a.imu.gyro_radps)
    # random access (the runner and the export read frames by index) gives the same frames
    assert np.array_equal(bag[2].image, src[2].image) and np.array_equal(bag[0].image, src[0].image)


def test_raw_images_and_16bit_depth(tmp_path: Path, frames: tuple[list, object]) -> None:
    src, camera = frames
    path = write_room_bag(tmp_path / "raw.bag", src, camera, "ros1", raw=True, depth=True)
    bag = RosbagDataset(path, RAW_TOPIC, depth_topic=DEPTH_TOPIC, camera_info_topic=INFO_TOPIC)
    for a, b in zip(src, bag, strict=True):
        assert np.array_equal(b.image, a.image)
        assert b.depth_m is not None and b.depth_m.dtype == np.float32
        assert np.max(np.abs(b.depth_m - np.nan_to_num(a.depth_m))) <= 0.0005 + 1e-6  # millimetres


def test_the_config_group_builds_it(tmp_path: Path, frames: tuple[list, object]) -> None:
    src, camera = frames
    path = write_room_bag(tmp_path / "room.bag", src, camera, "ros1")
    cfg = compose_config(
        ["dataset=rosbag", f"dataset.path={path}", f"dataset.image_topic={IMAGE_TOPIC}",
         f"dataset.camera_info_topic={INFO_TOPIC}", "dataset.max_frames=3"]
    )  # fmt: skip
    built = build_components(cfg, ComponentRegistry.discover())
    assert isinstance(built["dataset"], RosbagDataset) and len(built["dataset"]) == 3


def test_a_missing_topic_names_the_bag_the_topic_and_what_the_bag_has(
    tmp_path: Path, frames: tuple[list, object]
) -> None:
    src, camera = frames
    path = write_room_bag(tmp_path / "room.bag", src, camera, "ros1")
    with pytest.raises(DatasetError, match=r"room\.bag: no topic /cam1/image \(dataset\.image_topic\).*/imu0"):
        RosbagDataset(path, "/cam1/image")
    with pytest.raises(DatasetError, match=r"topic /imu0 \(dataset\.image_topic\) is sensor_msgs/msg/Imu"):
        RosbagDataset(path, IMU_TOPIC)


@pytest.mark.parametrize("kind", ["ros1", "mcap"])
def test_a_truncated_bag_is_a_clear_error(tmp_path: Path, frames: tuple[list, object], kind: str) -> None:
    src, camera = frames
    path = write_room_bag(bag_path(tmp_path, kind), src, camera, kind)
    data_file = path if kind == "ros1" else next(path.glob("*.mcap"))
    data = data_file.read_bytes()
    data_file.write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError, match=str(path.name)):
        bag = RosbagDataset(path, IMAGE_TOPIC, camera_info_topic=INFO_TOPIC)
        list(bag)


def test_an_image_unlike_the_calibration_names_the_bag_topic_and_message(
    tmp_path: Path, frames: tuple[list, object]
) -> None:
    src, camera = frames

    def shrink(index: int, grey: np.ndarray) -> np.ndarray:
        return grey[::2, ::2].copy() if index == 2 else grey

    path = write_room_bag(tmp_path / "room.bag", src, camera, "ros1", image_hook=shrink)
    bag = RosbagDataset(path, IMAGE_TOPIC, camera_info_topic=INFO_TOPIC)
    bag[1]
    with pytest.raises(CalibrationError, match=rf"room\.bag: topic {IMAGE_TOPIC}, message 2: the image is 320x240 px"):
        bag[2]


def test_a_path_that_is_not_a_bag(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="no such file"):
        RosbagDataset(tmp_path / "nothing.bag", IMAGE_TOPIC)
    (tmp_path / "text.bag").write_text("not a bag\n")
    with pytest.raises(DatasetError, match=r"text\.bag: not a readable"):
        RosbagDataset(tmp_path / "text.bag", IMAGE_TOPIC)


def test_node_keys_are_the_constructor_keywords() -> None:
    """conf/dataset/rosbag.yaml names every keyword of the reader, each with a comment (as the other datasets')."""
    import inspect

    from omegaconf import OmegaConf

    path = Path(__file__).resolve().parents[3] / "conf" / "dataset" / "rosbag.yaml"
    cfg = OmegaConf.load(path)
    assert sorted(str(k) for k in cfg if k != "_target_") == sorted(inspect.signature(RosbagDataset).parameters)
    assert OmegaConf.is_missing(cfg, "path") and OmegaConf.is_missing(cfg, "image_topic")
    for line in path.read_text().splitlines():
        if line and not line.startswith("#") and not line.startswith("_target_"):
            assert "#" in line, f"{path.name}: option without a comment: {line}"
