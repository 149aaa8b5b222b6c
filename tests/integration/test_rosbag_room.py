"""dataset=rosbag through a whole run (issue 18.4 "done when"): a ROS 1 bag and a ROS 2 bag written from the
synthetic room (PNG-compressed images, IMU, camera_info) give the same trajectory as the synthetic dataset itself,
with the sequential runner."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf
from rosbag_room import IMAGE_TOPIC, IMU_TOPIC, INFO_TOPIC, write_room_bag

from slamkit.app import build_components, build_runner
from slamkit.config import compose_config
from slamkit.io.trajectory_io import read_trajectory
from slamkit.plugins import ComponentRegistry
from slamkit.sensors import Trajectory

pytest.importorskip("rosbags", reason="rosbags reads and writes the bags")

#: The room's first 45 frames: initialised at frame 10, then tracked (8 keyframes).
FRAMES = 45


def run(run_dir: Path, overrides: list[str]) -> Trajectory:
    cfg = compose_config(["runner=sequential", "runner.progress=false", *overrides])
    runner, dataset = build_runner(cfg)
    config = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(config, dict)
    runner.run(dataset, dataset.camera, run_dir=run_dir, config={str(k): v for k, v in config.items()})
    return read_trajectory(run_dir / "trajectory.tum", "tum")


def test_ros1_and_ros2_bags_of_the_room_give_the_room_trajectory(tmp_path: Path) -> None:
    room = build_components(compose_config([f"dataset.max_frames={FRAMES}"]), ComponentRegistry.discover())["dataset"]
    frames = list(room)
    reference = run(tmp_path / "synthetic", [f"dataset.max_frames={FRAMES}"])
    assert len(reference) >= FRAMES - 12  # tracked from its initialisation on
    for kind, name in (("ros1", "room.bag"), ("ros2", "room_ros2")):
        bag = write_room_bag(tmp_path / name, frames, room.camera, kind)
        got = run(
            tmp_path / f"run_{kind}",
            ["dataset=rosbag", f"dataset.path={bag}", f"dataset.image_topic={IMAGE_TOPIC}",
             f"dataset.imu_topic={IMU_TOPIC}", f"dataset.camera_info_topic={INFO_TOPIC}"],
        )  # fmt: skip
        assert len(got) == len(reference), kind
        np.testing.assert_allclose(got.t_s, reference.t_s, rtol=0, atol=1e-9)
        assert np.array_equal(got.T_w_c, reference.T_w_c), f"{kind}: the poses differ from the synthetic run's"
