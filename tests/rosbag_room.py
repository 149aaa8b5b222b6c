"""Bags written from the synthetic world with rosbags' own writers, for the rosbag dataset's tests: ROS 1 (.bag),
ROS 2 (sqlite3 or MCAP storage), with PNG-compressed (lossless) or raw images, IMU and camera_info."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from slamkit.io.synthetic.dataset import SyntheticDataset
from slamkit.sensors import FrameData

IMAGE_TOPIC = "/cam0/image/compressed"
RAW_TOPIC = "/cam0/image_raw"
DEPTH_TOPIC = "/cam0/depth"
IMU_TOPIC = "/imu0"
INFO_TOPIC = "/cam0/camera_info"


def _ns(t_s: float) -> int:
    return round(t_s * 1e9)


def write_room_bag(
    path: Path,
    frames: Iterable[FrameData],
    camera: Any,
    kind: str = "ros2",
    raw: bool = False,
    depth: bool = False,
    image_hook: Any = None,
) -> Path:
    """Write ``frames`` (and their IMU samples, a camera_info of ``camera``) as a bag: kind "ros1" (a .bag file),
    "ros2" (sqlite3) or "mcap" (ROS 2 bag with MCAP storage). Images PNG-compressed (``IMAGE_TOPIC``) or raw mono8
    (``RAW_TOPIC``, ``raw``); depth 16UC1 mm (``DEPTH_TOPIC``). image_hook(index, grey) -> grey alters an image."""
    from rosbags.typesys import Stores, get_typestore

    ros1 = kind == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    T = ts.types
    Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
    if ros1:
        from rosbags.rosbag1 import Writer as Writer1

        writer: Any = Writer1(path)
    else:
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Writer2

        storage = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(path, version=9, storage_plugin=storage)

    def header(t_ns: int, seq: int, frame_id: str = "cam0") -> Any:
        stamp = Time(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)
        return Header(seq=seq, stamp=stamp, frame_id=frame_id) if ros1 else Header(stamp=stamp, frame_id=frame_id)

    def ser(msg: Any) -> bytes:
        return bytes(ts.serialize_ros1(msg, msg.__msgtype__) if ros1 else ts.serialize_cdr(msg, msg.__msgtype__))

    with writer:
        image_type = "sensor_msgs/msg/Image" if raw else "sensor_msgs/msg/CompressedImage"
        c_img = writer.add_connection(RAW_TOPIC if raw else IMAGE_TOPIC, image_type, typestore=ts)
        c_imu = writer.add_connection(IMU_TOPIC, "sensor_msgs/msg/Imu", typestore=ts)
        c_info = writer.add_connection(INFO_TOPIC, "sensor_msgs/msg/CameraInfo", typestore=ts)
        c_depth = writer.add_connection(DEPTH_TOPIC, "sensor_msgs/msg/Image", typestore=ts) if depth else None
        Vec, Quat = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
        Roi = T["sensor_msgs/msg/RegionOfInterest"]
        K = camera.K
        info_kwargs = dict(
            height=camera.height,
            width=camera.width,
            distortion_model="plumb_bob",
            binning_x=0,
            binning_y=0,
            roi=Roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
        )
        d, k, r = np.asarray(camera.dist, np.float64), K.ravel().astype(np.float64), np.eye(3).ravel()
        p = np.hstack([K, np.zeros((3, 1))]).ravel()
        if ros1:
            info = T["sensor_msgs/msg/CameraInfo"](header=header(0, 0), D=d, K=k, R=r, P=p, **info_kwargs)
        else:
            info = T["sensor_msgs/msg/CameraInfo"](header=header(0, 0), d=d, k=k, r=r, p=p, **info_kwargs)
        writer.write(c_info, 0, ser(info))
        for frame in frames:
            for t, a, w in zip(frame.imu.t_s, frame.imu.acc_mps2, frame.imu.gyro_radps, strict=True):
                imu = T["sensor_msgs/msg/Imu"](
                    header=header(_ns(t), 0, "imu0"),
                    orientation=Quat(x=0.0, y=0.0, z=0.0, w=1.0),
                    orientation_covariance=np.zeros(9),
                    angular_velocity=Vec(x=w[0], y=w[1], z=w[2]),
                    angular_velocity_covariance=np.zeros(9),
                    linear_acceleration=Vec(x=a[0], y=a[1], z=a[2]),
                    linear_acceleration_covariance=np.zeros(9),
                )
                writer.write(c_imu, _ns(t), ser(imu))
            t_ns = _ns(frame.timestamp_s)
            grey = frame.image if image_hook is None else image_hook(frame.index, frame.image)
            if raw:
                h, w_ = grey.shape
                msg = T["sensor_msgs/msg/Image"](
                    header=header(t_ns, frame.index), height=h, width=w_, encoding="mono8", is_bigendian=0,
                    step=w_, data=np.ascontiguousarray(grey).ravel(),
                )  # fmt: skip
            else:
                ok, png = cv2.imencode(".png", grey)
                assert ok
                msg = T["sensor_msgs/msg/CompressedImage"](
                    header=header(t_ns, frame.index), format="mono8; png compressed", data=png.ravel()
                )
            writer.write(c_img, t_ns, ser(msg))
            if c_depth is not None and frame.depth_m is not None:
                mm = np.round(np.nan_to_num(frame.depth_m) * 1000.0).astype("<u2")
                h, w_ = mm.shape
                dmsg = T["sensor_msgs/msg/Image"](
                    header=header(t_ns, frame.index), height=h, width=w_, encoding="16UC1", is_bigendian=0,
                    step=2 * w_, data=mm.view(np.uint8).ravel(),
                )  # fmt: skip
                writer.write(c_depth, t_ns, ser(dmsg))
    return path


def room(max_frames: int, **kwargs: Any) -> SyntheticDataset:
    """The synthetic room as the default config renders it (seed 0), first ``max_frames`` frames."""
    return SyntheticDataset(scene="room", seed=0, max_frames=max_frames, **kwargs)
