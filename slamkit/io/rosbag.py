"""Recordings as datasets: ROS 1 bags (``.bag``), ROS 2 bags (a folder with ``metadata.yaml``, sqlite3 or MCAP
storage) and bare MCAP files, read with the ``rosbags`` package (no ROS installation needed).

Topics come from the config (conf/dataset/rosbag.yaml): the image topic (``sensor_msgs/Image`` raw, or
``sensor_msgs/CompressedImage``: PNG, JPEG, whatever OpenCV decodes), optionally a depth topic (``16UC1`` in
millimetres, ``32FC1`` in metres, associated to each image by the nearest stamp), an IMU topic
(``sensor_msgs/Imu``: the samples between consecutive frames) and a ``sensor_msgs/CameraInfo`` topic for the
calibration (``plumb_bob`` / ``rational_polynomial`` -> pinhole with k1 k2 p1 p2 k3, ``equidistant`` ->
Kannala-Brandt), unless ``camera`` or ``settings`` gives it. Times are the messages' header stamps.

Errors name the bag and the topic: a topic missing (with the topics the bag has), a file that is not a bag or is
truncated, an image whose size disagrees with the calibration, an encoding slamkit cannot read.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from slamkit.errors import CalibrationError, ConfigError, DatasetError, FrameReadError
from slamkit.geometry.camera import KannalaBrandtCamera, PinholeCamera
from slamkit.interfaces import Camera
from slamkit.io.base import SequenceDataset
from slamkit.io.calibration import camera_from_options, load_settings, orb_extractor_from_options
from slamkit.sensors import FrameData, ImuSamples

log = logging.getLogger("slamkit.io")

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
U8 = NDArray[np.uint8]

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")


def _stamp_ns(msg: Any) -> int:
    stamp = msg.header.stamp
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _open_reader(path: Path) -> Any:
    """An opened rosbags AnyReader of ``path``; DatasetError naming the bag when it is not a readable bag."""
    from rosbags.highlevel import AnyReader

    if not path.exists():
        raise DatasetError(f"bag {path}: no such file or folder (dataset.path)")
    try:
        reader = AnyReader([path])
        reader.open()
    except Exception as exc:  # rosbags raises its own error types per format (ReaderError, AnyReaderError, ...)
        raise DatasetError(f"bag {path}: not a readable ROS 1 / ROS 2 bag or MCAP file ({exc})") from exc
    return reader


class RosbagDataset(SequenceDataset):
    """The frames of one image topic of a bag (see the module docstring). Constructor keywords are the keys of
    conf/dataset/rosbag.yaml."""

    def __init__(
        self,
        path: str | Path,
        image_topic: str,
        skip: Sequence[int] | None = None,
        max_frames: int | None = None,
        depth_topic: str | None = None,
        imu_topic: str | None = None,
        camera_info_topic: str | None = None,
        camera: Mapping[str, Any] | None = None,
        settings: str | Path | None = None,
        fps: float | None = None,
        depth_scale_16u: float = 1e-3,
        depth_max_dt_s: float = 0.02,
        use_depth: bool | None = None,
    ) -> None:
        self.path = Path(path)
        self.name = f"rosbag:{self.path.name}"
        self.image_topic = str(image_topic)
        self.depth_topic = None if depth_topic is None or use_depth is False else str(depth_topic)
        self._depth_scale = float(depth_scale_16u)
        self._depth_max_dt_ns = round(float(depth_max_dt_s) * 1e9)
        self._reader = _open_reader(self.path)
        self._cursor: Iterator[tuple[Any, int, bytes]] | None = None  # the image messages, read on in order
        self._cursor_next = 0  # the raw index the cursor gives next
        try:
            self._image_conn = self._connection(self.image_topic, IMAGE_TYPES, "dataset.image_topic")
            self._image_log_ns, self._image_stamp_ns = self._index(self._image_conn, self.image_topic)
            if self._image_stamp_ns.size == 0:
                raise DatasetError(f"bag {self.path}: topic {self.image_topic} has no message")
            self._depth_conn = None
            if self.depth_topic is not None:
                self._depth_conn = self._connection(self.depth_topic, ("sensor_msgs/msg/Image",), "dataset.depth_topic")
                self._depth_log_ns, self._depth_stamp_ns = self._index(self._depth_conn, self.depth_topic)
            self._imu = self._read_imu(imu_topic) if imu_topic else None
            info_camera = self._camera_info(camera_info_topic) if camera_info_topic else None
        except BaseException:
            self._reader.close()
            raise
        self._t_s: F64 = self._image_stamp_ns.astype(np.float64) * 1e-9
        first = self._decode_image(0)
        size = (int(first.shape[1]), int(first.shape[0]))
        if info_camera is not None and (camera is not None or settings is not None):
            raise ConfigError("dataset.camera_info_topic and dataset.camera / dataset.settings are all set; give one")
        loaded = load_settings(settings, size)
        self.orb_settings = orb_extractor_from_options(None, loaded)
        if info_camera is not None:
            self.camera: Camera = info_camera
            self._calib = f"topic {camera_info_topic} of bag {self.path}"
        else:
            self.camera, self._calib = camera_from_options(camera, loaded, size)
        if fps is None:
            steps = np.diff(self._image_stamp_ns)
            fps = round(1e9 / float(np.median(steps)), 3) if steps.size else 30.0
        if float(fps) <= 0:
            raise ConfigError(f"dataset.fps must be positive, got {fps}")
        self.fps = float(fps)
        self._setup_selection(skip, max_frames)

    # ---- the bag's index ----------------------------------------------------------------------

    def _connection(self, topic: str, types: Sequence[str], key: str) -> Any:
        conns = [c for c in self._reader.connections if c.topic == topic]
        if not conns:
            have = ", ".join(sorted({f"{c.topic} ({c.msgtype})" for c in self._reader.connections})) or "none"
            raise DatasetError(f"bag {self.path}: no topic {topic} ({key}); the bag's topics: {have}")
        if conns[0].msgtype not in types:
            raise DatasetError(
                f"bag {self.path}: topic {topic} ({key}) is {conns[0].msgtype}; expected {' or '.join(types)}"
            )
        return conns[0]

    def _messages(self, conn: Any, topic: str, start: int | None = None, stop: int | None = None) -> Iterator[Any]:
        """(connection, log time ns, raw bytes) of one connection, in log-time order; DatasetError naming the bag
        and topic when the bag breaks off (a truncated file)."""
        try:
            yield from self._reader.messages(connections=[conn], start=start, stop=stop)
        except Exception as exc:
            raise DatasetError(f"bag {self.path}: topic {topic} cannot be read to the end ({exc})") from exc

    def _deserialize(self, raw: bytes, conn: Any, topic: str) -> Any:
        try:
            return self._reader.deserialize(raw, conn.msgtype)
        except Exception as exc:
            raise DatasetError(f"bag {self.path}: a message of topic {topic} cannot be decoded ({exc})") from exc

    def _index(self, conn: Any, topic: str) -> tuple[I64, I64]:
        """(log times, header stamps) ns of every message of the topic, in log-time order (each deserialized once:
        the header is at the front, but the message types give no cheaper way)."""
        log_ns, stamp_ns = [], []
        for _, t, raw in self._messages(conn, topic):
            log_ns.append(int(t))
            stamp_ns.append(_stamp_ns(self._deserialize(raw, conn, topic)))
        stamps = np.array(stamp_ns, np.int64)
        if stamps.size > 1 and np.any(np.diff(stamps) <= 0):
            raise DatasetError(f"bag {self.path}: topic {topic}: header stamps are not strictly increasing")
        return np.array(log_ns, np.int64), stamps

    def _read_imu(self, topic: str) -> tuple[F64, F64, F64]:
        conn = self._connection(topic, ("sensor_msgs/msg/Imu",), "dataset.imu_topic")
        t, acc, gyro = [], [], []
        for _, _, raw in self._messages(conn, topic):
            msg = self._deserialize(raw, conn, topic)
            t.append(_stamp_ns(msg))
            a, w = msg.linear_acceleration, msg.angular_velocity
            acc.append((a.x, a.y, a.z))
            gyro.append((w.x, w.y, w.z))
        t_ns = np.array(t, np.int64)
        if t_ns.size > 1 and np.any(np.diff(t_ns) <= 0):
            raise DatasetError(f"bag {self.path}: topic {topic}: IMU stamps are not strictly increasing")
        return t_ns.astype(np.float64) * 1e-9, np.array(acc, np.float64).reshape(-1, 3), np.array(gyro).reshape(-1, 3)

    def _camera_info(self, topic: str) -> Camera:
        """The calibration of the first CameraInfo message of ``topic``."""
        conn = self._connection(topic, ("sensor_msgs/msg/CameraInfo",), "dataset.camera_info_topic")
        for _, _, raw in self._messages(conn, topic):
            msg = self._deserialize(raw, conn, topic)
            # ROS 1 names the fields K and D, ROS 2 k and d
            K = np.asarray(getattr(msg, "k", None) if hasattr(msg, "k") else msg.K, np.float64).reshape(3, 3)
            d = [float(x) for x in np.asarray(msg.d if hasattr(msg, "d") else msg.D, np.float64).ravel()]
            where = f"bag {self.path}: topic {topic}"
            if K[0, 0] <= 0 or K[1, 1] <= 0:
                raise CalibrationError(f"{where}: K has no focal lengths ({K.ravel().tolist()})")
            args = (int(msg.width), int(msg.height), K[0, 0], K[1, 1], K[0, 2], K[1, 2])
            if msg.distortion_model == "equidistant":
                return KannalaBrandtCamera(*args, k=(d + [0.0] * 4)[:4])
            if msg.distortion_model in ("plumb_bob", "rational_polynomial", ""):
                if any(x != 0.0 for x in d[5:]):
                    raise CalibrationError(f"{where}: rational_polynomial coefficients k4..k6 are not supported")
                return PinholeCamera(*args, dist=(d + [0.0] * 5)[:5])
            raise CalibrationError(f"{where}: distortion model {msg.distortion_model!r} is not supported")
        raise DatasetError(f"bag {self.path}: topic {topic} (dataset.camera_info_topic) has no message")

    # ---- frames ------------------------------------------------------------------------------

    def _n_raw(self) -> int:
        return int(self._image_stamp_ns.shape[0])

    def timestamps(self) -> F64:
        """(N,) s header stamps of the yielded frames."""
        return self._t_s[self.raw_indices()]

    def _raw_image(self, raw_index: int) -> Any:
        """The image message ``raw_index``: read on from the last one when the frames go in order (a run), else
        looked up by its log time."""
        if self._cursor is None or raw_index != self._cursor_next:
            self._cursor = self._messages(self._image_conn, self.image_topic, start=int(self._image_log_ns[raw_index]))
            # messages before raw_index with the same log time
            same = int(np.count_nonzero(self._image_log_ns[:raw_index] == self._image_log_ns[raw_index]))
            for _ in range(same):
                next(self._cursor)
        try:
            _, _, raw = next(self._cursor)
        except StopIteration:
            raise DatasetError(f"bag {self.path}: topic {self.image_topic} ended before message {raw_index}") from None
        self._cursor_next = raw_index + 1
        return self._deserialize(raw, self._image_conn, self.image_topic)

    def _decode_image(self, raw_index: int) -> U8:
        """(H, W) or (H, W, 3) BGR uint8 of image message ``raw_index``."""
        msg = self._raw_image(raw_index)
        where = f"bag {self.path}: topic {self.image_topic}, message {raw_index}"
        if self._image_conn.msgtype == "sensor_msgs/msg/CompressedImage":
            image = cv2.imdecode(
                np.frombuffer(np.asarray(msg.data, np.uint8).tobytes(), np.uint8), cv2.IMREAD_UNCHANGED
            )
            if image is None:
                raise FrameReadError(f"{where}: the {msg.format!r} image cannot be decoded")
            if image.dtype != np.uint8:
                raise FrameReadError(f"{where}: {image.dtype} image; expected 8 bits")
            if image.ndim == 3 and image.shape[2] == 4:
                image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
            return np.ascontiguousarray(image)
        return _raw_image_array(msg, where, colour=True)

    def _load(self, raw_index: int, out_index: int) -> FrameData:
        image = self._decode_image(raw_index)
        where = f"bag {self.path}: topic {self.image_topic}, message {raw_index}"
        h, w = image.shape[:2]
        if (w, h) != (self.camera.width, self.camera.height):
            raise CalibrationError(
                f"{where}: the image is {w}x{h} px but the calibration ({self._calib}) is "
                f"{self.camera.width}x{self.camera.height} px"
            )
        colour = image if image.ndim == 3 else None
        grey = image if image.ndim == 2 else np.asarray(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), np.uint8)
        stamp = int(self._image_stamp_ns[raw_index])
        return FrameData(
            index=out_index,
            timestamp_s=float(self._t_s[raw_index]),
            image=grey,
            color=colour,
            depth_m=self._depth(stamp, where) if self._depth_conn is not None else None,
            imu=self._imu_between(raw_index),
            source=where,
        )

    def _imu_between(self, raw_index: int) -> ImuSamples:
        """The IMU samples with stamps in (previous image's stamp, this image's stamp]."""
        if self._imu is None:
            return ImuSamples.empty()
        t, acc, gyro = self._imu
        hi = self._t_s[raw_index]
        lo = self._t_s[raw_index - 1] if raw_index > 0 else -np.inf
        sel = (t > lo) & (t <= hi)
        return ImuSamples(t[sel], acc[sel], gyro[sel])

    def _depth(self, stamp_ns: int, where: str) -> NDArray[np.float32] | None:
        """The depth image nearest in stamp (within depth_max_dt_s), metres; None when there is none."""
        assert self._depth_conn is not None and self.depth_topic is not None
        if self._depth_stamp_ns.size == 0:
            return None
        i = int(np.argmin(np.abs(self._depth_stamp_ns - stamp_ns)))
        if abs(int(self._depth_stamp_ns[i]) - stamp_ns) > self._depth_max_dt_ns:
            return None
        log_t = int(self._depth_log_ns[i])
        for _, _, raw in self._messages(self._depth_conn, self.depth_topic, start=log_t, stop=log_t + 1):
            msg = self._deserialize(raw, self._depth_conn, self.depth_topic)
            if _stamp_ns(msg) != int(self._depth_stamp_ns[i]):
                continue
            depth = _raw_image_array(msg, f"bag {self.path}: topic {self.depth_topic}", colour=False)
            if depth.shape[:2] != (self.camera.height, self.camera.width):
                raise CalibrationError(
                    f"bag {self.path}: topic {self.depth_topic}: depth image {depth.shape[1]}x{depth.shape[0]} px "
                    f"but the calibration is {self.camera.width}x{self.camera.height} px"
                )
            if depth.dtype == np.uint16:
                return (depth.astype(np.float32) * np.float32(self._depth_scale)).astype(np.float32)
            return np.nan_to_num(depth.astype(np.float32), nan=0.0)
        return None

    def close(self) -> None:
        self._reader.close()


#: sensor_msgs/Image encodings slamkit reads -> (numpy dtype, channels, conversion to BGR or None)
_ENCODINGS: dict[str, tuple[str, int, int | None]] = {
    "mono8": ("u1", 1, None),
    "8UC1": ("u1", 1, None),
    "bgr8": ("u1", 3, None),
    "rgb8": ("u1", 3, cv2.COLOR_RGB2BGR),
    "bgra8": ("u1", 4, cv2.COLOR_BGRA2BGR),
    "rgba8": ("u1", 4, cv2.COLOR_RGBA2BGR),
    "16UC1": ("u2", 1, None),
    "mono16": ("u2", 1, None),
    "32FC1": ("f4", 1, None),
}


def _raw_image_array(msg: Any, where: str, colour: bool) -> NDArray[Any]:
    """The pixels of a sensor_msgs/Image: (H, W) or (H, W, 3) BGR."""
    enc = str(msg.encoding)
    if enc not in _ENCODINGS:
        raise FrameReadError(f"{where}: image encoding {enc!r}; expected one of {', '.join(_ENCODINGS)}")
    dtype, channels, conversion = _ENCODINGS[enc]
    np_dtype = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, np.uint8)
    row_bytes = w * channels * np_dtype.itemsize
    if step < row_bytes or data.size < h * step:
        raise FrameReadError(f"{where}: {data.size} bytes for a {w}x{h} {enc} image (step {step})")
    rows = data[: h * step].reshape(h, step)[:, :row_bytes]
    image = (
        np.ascontiguousarray(rows).view(np_dtype).reshape(h, w, channels)
        if channels > 1
        else (np.ascontiguousarray(rows).view(np_dtype).reshape(h, w))
    )
    image = image.astype(np_dtype.newbyteorder("="), copy=False)
    if conversion is not None:
        image = cv2.cvtColor(image, conversion)
    if not colour and image.ndim == 3:
        raise FrameReadError(f"{where}: a {enc} image where one channel was expected")
    return np.ascontiguousarray(image)
