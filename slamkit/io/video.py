"""A video file (read with cv2.VideoCapture) as a monocular sequence, and what every OpenCV capture shares.

The frames are counted by decoding the file once when the dataset is built (container frame counts are
often wrong); frame k has time ``k / fps`` with fps from the file unless ``fps`` is given. Frames are
read sequentially; asking for an earlier frame reopens the file and skips forward, so random access is
exact but slow.

Shared with the live camera (slamkit/io/camera.py): opening a capture (:func:`open_capture`), the calibration
of a capture's frames (:func:`capture_calibration`: ``dataset.camera`` or ``dataset.settings``, sized by the
first frame) and a decoded frame as FrameData (:func:`capture_frame_data`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from slamkit.errors import ConfigError, DatasetError
from slamkit.interfaces import Camera
from slamkit.io.base import SequenceDataset
from slamkit.io.calibration import camera_from_options, load_settings, orb_extractor_from_options
from slamkit.io.images import check_size
from slamkit.io.orbslam_settings import OrbExtractorSettings
from slamkit.io.textfiles import require_file
from slamkit.sensors import FrameData

U8 = NDArray[np.uint8]


def open_capture(source: int | str, api: int = cv2.CAP_ANY, what: str = "", hint: str = "") -> cv2.VideoCapture:
    """An opened cv2.VideoCapture of ``source`` (a device index, a file, a URL or a GStreamer pipeline) through the
    capture API ``api`` (cv2.CAP_ANY: the first that opens it). OpenCV's own warnings while it tries its backends
    are silenced: a source that does not open is one DatasetError "``what`` could not be opened ``hint``"."""
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    try:
        cap = cv2.VideoCapture(source, api)
        opened = cap.isOpened()
    finally:
        cv2.utils.logging.setLogLevel(level)
    if not opened:
        raise DatasetError(f"{what or source} could not be opened{hint}")
    return cap


def capture_calibration(
    camera: Mapping[str, Any] | None, settings: str | Path | None, size: tuple[int, int]
) -> tuple[OrbExtractorSettings | None, Camera, str]:
    """The calibration of a capture's frames of ``size`` (W, H) px: ``dataset.camera`` (width/height default to
    ``size``) or ``dataset.settings`` (an ORB-SLAM settings file) -> (its ORB extractor settings, the camera, where
    the calibration came from)."""
    loaded = load_settings(settings, size)
    cam, calib = camera_from_options(camera, loaded, size)
    return orb_extractor_from_options(None, loaded), cam, calib


def capture_frame_data(
    frame: U8, index: int, timestamp_s: float, source: str, camera: Camera, calib: str, what: str = "image file"
) -> FrameData:
    """A decoded capture frame, (H, W, 3) BGR or (H, W) grey uint8, as FrameData: grey image + BGR colour. Its size
    is checked against ``camera`` (CalibrationError naming ``what`` ``source`` and ``calib``)."""
    check_size(Path(source), int(frame.shape[1]), int(frame.shape[0]), (camera.width, camera.height), calib, what)
    color: U8 | None = None
    grey: U8 = frame
    if frame.ndim == 3:
        color = np.ascontiguousarray(frame[:, :, :3])
        grey = np.asarray(cv2.cvtColor(color, cv2.COLOR_BGR2GRAY), dtype=np.uint8)
    return FrameData(index=index, timestamp_s=timestamp_s, image=grey, color=color, source=source)


def _open(path: Path) -> cv2.VideoCapture:
    return open_capture(str(path), what=f"video file {path}", hint=" (unreadable or not a video OpenCV can decode)")


class VideoDataset(SequenceDataset):
    """Frames of a video file: grey + BGR colour; no depth or ground truth.

    Constructor keywords are the keys of conf/dataset/video.yaml:
    root: the video file. fps: frame rate (Hz) overriding the file's. camera / settings: as for folder.
    """

    _cap: cv2.VideoCapture | None = None  # class default: __del__ is safe when __init__ raised

    def __init__(
        self,
        root: str | Path,
        skip: Sequence[int] | None = None,
        max_frames: int | None = None,
        fps: float | None = None,
        camera: Mapping[str, Any] | None = None,
        settings: str | Path | None = None,
    ) -> None:
        self.path = require_file(Path(root), "video (dataset.root)")
        self.name = f"video:{self.path.name}"
        cap = _open(self.path)
        try:
            file_fps = float(cap.get(cv2.CAP_PROP_FPS))
            ok, first = cap.read()
            if not ok or first is None:
                raise DatasetError(f"video file {self.path} has no decodable frame")
            n = 1
            while cap.grab():
                n += 1
        finally:
            cap.release()
        self._n = n
        if fps is not None:
            if float(fps) <= 0:
                raise ConfigError(f"dataset.fps must be positive, got {fps}")
            self.fps = float(fps)
        elif np.isfinite(file_fps) and file_fps > 0:
            self.fps = file_fps
        else:
            raise ConfigError(f"video file {self.path} does not state its frame rate; set dataset.fps")
        size = (int(first.shape[1]), int(first.shape[0]))
        self.orb_settings, self.camera, self._calib = capture_calibration(camera, settings, size)
        self._cap: cv2.VideoCapture | None = None
        self._next = 0  # raw index the open capture will return next
        self._setup_selection(skip, max_frames)

    def _n_raw(self) -> int:
        return self._n

    def _read_raw(self, raw_index: int) -> U8:
        if self._cap is None or raw_index < self._next:
            if self._cap is not None:
                self._cap.release()
            self._cap = _open(self.path)
            self._next = 0
        while self._next < raw_index:
            if not self._cap.grab():
                raise DatasetError(f"video file {self.path}: frame {self._next} could not be read (truncated?)")
            self._next += 1
        ok, frame = self._cap.read()
        if not ok or frame is None:
            raise DatasetError(f"video file {self.path}: frame {raw_index} could not be decoded (truncated?)")
        self._next += 1
        return np.asarray(frame, dtype=np.uint8)

    def _load(self, raw_index: int, out_index: int) -> FrameData:
        frame = self._read_raw(raw_index)
        source = f"{self.path}#frame{raw_index}"
        return capture_frame_data(frame, out_index, raw_index / self.fps, source, self.camera, self._calib)

    def close(self) -> None:
        """Release the open capture (also done when the dataset is garbage-collected)."""
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def __del__(self) -> None:
        self.close()
