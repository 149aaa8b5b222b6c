"""A live capture device or stream through OpenCV (``dataset=camera``): monocular, no length, no ground truth.

``dataset.device`` is a device index (0: the first camera, /dev/video0 on Linux) or a string cv2.VideoCapture
opens: an ``rtsp://`` or ``http://`` URL, a GStreamer pipeline, or a video file / image pattern
(``frames/%06d.png``) played as a live stream — how the tests drive it without a camera.

- **Live.** The dataset says so (``live = True``, slamkit.runtime.source.is_live): the threaded runner reads it
  continuously from its frame-source thread into its one-slot mailbox (a frame tracking had no time for is replaced
  by the newer one and counted as dropped), never queues stale frames, and has no frame count (``len`` raises
  TypeError; slamkit.runtime.source.frame_count is None). A device or URL delivers frames at its own rate; a file
  or image pattern is paced at its timestamps (``paced``, ``dataset.pace``), as a camera would deliver it.
- **Timestamps** (:class:`StreamClock`): the capture's own, CAP_PROP_POS_MSEC, while the backend gives one that
  increases; else the wall clock since the capture was opened (continuing from the last stamp, so times keep
  increasing when a backend's clock fails mid-stream). The log says which.
- **The end.** ``dataset.duration_s`` of stream time, ``dataset.max_frames`` frames, the end of a file, a stream
  that delivers no frame for ``dataset.read_timeout_s`` (logged: the run ends with its outputs), or Ctrl-C (the
  threaded runner). ``end_reason`` says which.
- **Calibration** as ``dataset=video``: ``dataset.camera`` or ``dataset.settings`` (slamkit/io/video.py
  capture_calibration). A calibration of another size is first asked of the device (CAP_PROP_FRAME_WIDTH /
  HEIGHT); a stream that still delivers another size is a CalibrationError naming the parameter.

Reads go through one daemon reader thread (:class:`CaptureReader`) so that a read that blocks (a stream that stopped
mid-read) is abandoned after ``read_timeout_s`` instead of hanging the run or the process's exit.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from slamkit.errors import CalibrationError, ConfigError, DatasetError
from slamkit.interfaces import Camera
from slamkit.io.orbslam_settings import OrbExtractorSettings
from slamkit.io.video import capture_calibration, capture_frame_data, open_capture
from slamkit.sensors import FrameData, Trajectory

log = logging.getLogger("slamkit.io")

U8 = NDArray[np.uint8]

#: How often a device or URL whose read failed is read again until ``read_timeout_s`` runs out, s.
READ_RETRY_S = 0.01


def parse_device(device: int | str) -> int | str:
    """``dataset.device`` -> a device index (an int, or a string of digits) or the URL / pipeline / path string."""
    if isinstance(device, bool) or not isinstance(device, int | str):
        raise ConfigError(f"dataset.device = {device!r}: expected a device index (0, 1, ...) or a URL / path string")
    if isinstance(device, int):
        if device < 0:
            raise ConfigError(f"dataset.device = {device}: a device index is >= 0")
        return device
    text = device.strip()
    if not text:
        raise ConfigError("dataset.device is empty: expected a device index (0, 1, ...) or a URL / path string")
    return int(text) if text.isdigit() else text


def capture_api(backend: str | None) -> int:
    """``dataset.backend`` (an OpenCV capture API name: v4l2, ffmpeg, gstreamer, dshow, msmf, avfoundation, images,
    ...; null or "any": the first that opens the source) -> its cv2.CAP_* constant."""
    if backend is None or str(backend).lower() == "any":
        return int(cv2.CAP_ANY)
    value = getattr(cv2, f"CAP_{str(backend).upper()}", None)
    if not isinstance(value, int) or str(backend).upper().startswith("PROP"):
        raise ConfigError(
            f"dataset.backend = {backend!r}: not an OpenCV capture API (e.g. v4l2, ffmpeg, gstreamer, dshow, msmf, "
            "avfoundation, images; null: any)"
        )
    return value


def is_file_source(source: int | str) -> bool:
    """Whether ``source`` is a video file or an image pattern on disk (not a device, URL or GStreamer pipeline)."""
    if not isinstance(source, str) or "://" in source or "!" in source:
        return False
    path = Path(source).expanduser()
    return path.is_file() or ("%" in path.name and path.parent.is_dir())


def _positive(value: float | int | None, key: str) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value <= 0:
        raise ConfigError(f"dataset.{key} = {value!r}: expected a positive number or null")
    return float(value)


class StreamClock:
    """Timestamps of a live stream's frames, s.

    The capture's own clock (CAP_PROP_POS_MSEC, ms) while the backend gives a finite, non-negative value that
    increases from frame to frame; from the first frame where it does not (a backend without one reports 0 or -1),
    the wall clock (time.perf_counter) — since opening when it fails on the first frame, else continuing from the
    last stamp, so timestamps always increase. ``kind`` says which clock stamps the frames now.
    """

    CAPTURE = "the capture's (CAP_PROP_POS_MSEC)"
    WALL = "the wall clock since opening"

    def __init__(self, opened_at_s: float, label: str) -> None:
        """opened_at_s: time.perf_counter() when the capture was opened. label: the source, for the log."""
        self.kind: str | None = None
        self._opened_at_s = opened_at_s
        self._label = label
        self._last_t: float | None = None
        self._last_pos_ms = -math.inf
        self._last_wall_s = opened_at_s

    def stamp(self, pos_ms: float, wall_s: float) -> float:
        """The timestamp (s) of a frame the capture reported at ``pos_ms`` (CAP_PROP_POS_MSEC) and that was read at
        the perf_counter time ``wall_s``."""
        capture_ok = math.isfinite(pos_ms) and pos_ms >= 0.0 and pos_ms > self._last_pos_ms
        if self.kind is None:
            self.kind = self.CAPTURE if capture_ok else self.WALL
            log.info("%s: frame timestamps from %s", self._label, self.kind)
        elif self.kind == self.CAPTURE and not capture_ok:
            self.kind = self.WALL
            log.warning(
                "%s: CAP_PROP_POS_MSEC went from %.3f to %.3f ms (not increasing): frame timestamps from the wall clock "
                "from now on",
                self._label,
                self._last_pos_ms,
                pos_ms,
            )
        if self.kind == self.CAPTURE:
            t = pos_ms / 1e3
        elif self._last_t is None:
            t = wall_s - self._opened_at_s
        else:
            t = self._last_t + max(wall_s - self._last_wall_s, 1e-6)
        self._last_t, self._last_pos_ms, self._last_wall_s = t, pos_ms, wall_s
        return t


@dataclass(frozen=True)
class _Read:
    """One read of the capture: the frame (None: none came) with its CAP_PROP_POS_MSEC and the wall time it was
    read at (perf_counter, s), or why no frame will come (``end``)."""

    frame: U8 | None = None
    pos_ms: float = math.nan
    wall_s: float = 0.0
    end: str | None = None


_RELEASE = object()


class CaptureReader:
    """A capture and the one daemon thread that reads it and, at the end, releases it.

    ``read(timeout_s)`` asks the thread for the next frame and waits at most ``timeout_s``: a read that blocks (a
    stream that stopped mid-read) is then abandoned (``hung``) and no other read is asked. ``close()`` has the
    thread release the capture after its current read, so a capture is never released under a running read, and
    a daemon thread blocked for good does not keep the process alive.
    """

    def __init__(self, cap: cv2.VideoCapture, name: str) -> None:
        self.cap = cap
        self.hung = False
        self._closed = False
        self._requests: queue.SimpleQueue[object] = queue.SimpleQueue()
        self._results: queue.SimpleQueue[tuple[bool, U8 | None, float] | BaseException] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._serve, name=name, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while self._requests.get() is not _RELEASE:
            try:
                ok, frame = self.cap.read()
                image = None if not ok or frame is None else np.asarray(frame, dtype=np.uint8)
                self._results.put((image is not None, image, float(self.cap.get(cv2.CAP_PROP_POS_MSEC))))
            except BaseException as exc:  # handed to the caller
                self._results.put(exc)
        self.cap.release()

    def read(self, timeout_s: float) -> tuple[bool, U8 | None, float] | None:
        """(ok, the (H, W[, 3]) uint8 frame or None, its CAP_PROP_POS_MSEC), or None when no answer came within
        ``timeout_s`` (the reader is then ``hung``)."""
        if self.hung or self._closed:
            return None
        self._requests.put(None)
        try:
            got = self._results.get(timeout=max(timeout_s, 0.0))
        except queue.Empty:
            self.hung = True
            return None
        if isinstance(got, BaseException):
            raise got
        return got

    def close(self) -> None:
        """Release the capture (after the read in progress, if any); waits for it unless a read is hung."""
        if self._closed:
            return
        self._closed = True
        self._requests.put(_RELEASE)
        if not self.hung:
            self._thread.join()


class CameraDataset:
    """A live capture device or stream (see the module docstring); constructor keywords are the keys of
    conf/dataset/camera.yaml.

    device: index or URL / pipeline / file. backend: OpenCV capture API name (null: any). fps: the frame rate asked
    of the device and given to tracking (null: the device's, else ``fallback_fps``). fallback_fps: the frame rate
    when neither states one (ORB-SLAM2 Tracking: a settings file's Camera.fps of 0 means 30). duration_s /
    max_frames: end after that much stream time (s) / that many frames (null: no limit). read_timeout_s: a stream
    that delivers no frame for this long has stopped (s). pace: release frames at their timestamps (null: for a file
    or image pattern, not for a device or URL). camera / settings: the calibration, as for ``dataset=video``.
    """

    live = True
    camera_right: Camera | None = None
    T_l_r: NDArray[np.float64] | None = None
    T_b_c: NDArray[np.float64] | None = None
    ground_truth: Trajectory | None = None
    _reader: CaptureReader | None = None  # class default: close() is safe when __init__ raised

    def __init__(
        self,
        device: int | str = 0,
        backend: str | None = None,
        fps: float | None = None,
        fallback_fps: float = 30.0,
        duration_s: float | None = None,
        max_frames: int | None = None,
        read_timeout_s: float = 5.0,
        pace: bool | None = None,
        camera: Mapping[str, Any] | None = None,
        settings: str | Path | None = None,
    ) -> None:
        self.source = parse_device(device)
        self.api = capture_api(backend)
        self.file = is_file_source(self.source)
        kind = "camera device" if isinstance(self.source, int) else "video file" if self.file else "stream"
        self.label = f"{kind} {self.source} (dataset.device)"
        self.name = f"camera:{self.source}"
        self.duration_s = _positive(duration_s, "duration_s")
        timeout = _positive(read_timeout_s, "read_timeout_s")
        if timeout is None:
            raise ConfigError("dataset.read_timeout_s is required: how long a stream may deliver no frame, s")
        self.read_timeout_s = timeout
        if max_frames is not None and (
            isinstance(max_frames, bool) or not isinstance(max_frames, int) or max_frames < 1
        ):
            raise ConfigError(f"dataset.max_frames = {max_frames!r}: expected a positive integer or null")
        self.max_frames = max_frames
        self.paced = self.file if pace is None else bool(pace)
        self.end_reason: str | None = None
        asked_fps = _positive(fps, "fps")
        fallback = _positive(fallback_fps, "fallback_fps")
        if fallback is None:
            raise ConfigError("dataset.fallback_fps is required: the frame rate when the device states none, Hz")
        self._reader = self._open()
        try:
            self._setup(camera, settings, asked_fps, fallback)
        except BaseException:
            self.close()
            raise

    def _setup(
        self, camera: Mapping[str, Any] | None, settings: str | Path | None, asked_fps: float | None, fallback: float
    ) -> None:
        """The calibration (sized by a first frame; its size asked of a device) and the frame rate."""
        assert self._reader is not None
        reader = self._reader
        cap = reader.cap
        if asked_fps is not None and not self.file:
            cap.set(cv2.CAP_PROP_FPS, asked_fps)
        first = self._probe(reader)
        size = (int(first.shape[1]), int(first.shape[0]))
        self.orb_settings: OrbExtractorSettings | None
        self.orb_settings, self.camera, self._calib = capture_calibration(camera, settings, size)
        wanted = (int(self.camera.width), int(self.camera.height))
        if size != wanted and not self.file:  # ask the device for the calibrated size, then look again
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, wanted[0])
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, wanted[1])
            first = self._probe(reader)
            size = (int(first.shape[1]), int(first.shape[0]))
        if size != wanted:
            raise CalibrationError(
                f"{self.label} delivers {size[0]}x{size[1]} px frames but {self._size_parameter()} is "
                f"{wanted[0]}x{wanted[1]} px"
            )
        stream_fps = float(cap.get(cv2.CAP_PROP_FPS))
        if asked_fps is not None:
            self.fps = asked_fps
        elif math.isfinite(stream_fps) and stream_fps > 0:
            self.fps = stream_fps
        else:
            self.fps = fallback
            log.info("%s states no frame rate: %.1f Hz assumed (dataset.fallback_fps)", self.label, fallback)
        if self.file:  # the stream starts at the file's first frame: reopened when it is read
            self.close()

    # ---- the Dataset protocol ---------------------------------------------------------------------

    def __len__(self) -> int:
        raise TypeError(f"{self.name} is a live source: it has no length (slamkit.runtime.source.frame_count)")

    def __iter__(self) -> Iterator[FrameData]:
        """The stream's frames, numbered 0, 1, ... in capture order, until one of the ends (``end_reason``). Read
        once per pass; a second pass opens the source again (a file: from its start)."""
        reader = self._reader if self._reader is not None else self._open()
        self._reader = None
        clock = StreamClock(time.perf_counter(), self.label)
        self.end_reason = None
        n = 0
        t_first: float | None = None
        try:
            while self.end_reason is None:
                if self.max_frames is not None and n >= self.max_frames:
                    self.end_reason = f"dataset.max_frames={self.max_frames} frames captured"
                    break
                got = self._read(reader)
                if got.frame is None:
                    self.end_reason = got.end or "end of stream"
                    break
                t = clock.stamp(got.pos_ms, got.wall_s)
                t_first = t if t_first is None else t_first
                if self.duration_s is not None and t - t_first >= self.duration_s:
                    self.end_reason = f"dataset.duration_s={self.duration_s:g} s of stream captured"
                    break
                yield capture_frame_data(
                    got.frame, n, t, f"{self.name}#frame{n}", self.camera, self._calib, what="camera frame"
                )
                n += 1
        finally:
            reader.close()
            log.info("%s: %d frames captured; %s", self.label, n, self.end_reason or "the run stopped reading")

    def close(self) -> None:
        """Release the capture opened to probe the source (a pass releases its own when it ends)."""
        if self._reader is not None:
            self._reader.close()
            self._reader = None

    def __del__(self) -> None:
        self.close()

    # ---- internals --------------------------------------------------------------------------------

    def _open(self) -> CaptureReader:
        hint = " (no such device, or it is busy or not permitted)"
        if not isinstance(self.source, int):
            hint = " (unreachable, or not a stream, pipeline or file OpenCV can decode)"
        return CaptureReader(open_capture(self.source, self.api, what=self.label, hint=hint), "camera-reader")

    def _probe(self, reader: CaptureReader) -> U8:
        """A frame read when the dataset is built (its size sizes the calibration); DatasetError when none comes."""
        got = self._read(reader)
        if got.frame is None:
            raise DatasetError(f"{self.label} opened but delivered no frame ({got.end})")
        return got.frame

    def _read(self, reader: CaptureReader) -> _Read:
        """The next frame, waiting at most ``read_timeout_s`` for it: a failed read of a device or URL is tried
        again until then (a file's is its end); a read still blocked then is abandoned."""
        deadline = time.perf_counter() + self.read_timeout_s
        stopped = f"no frame for {self.read_timeout_s:g} s (dataset.read_timeout_s): the stream stopped"
        while True:
            answer = reader.read(deadline - time.perf_counter())
            if answer is None:
                log.warning("%s: %s", self.label, stopped)
                return _Read(end=stopped)
            ok, frame, pos_ms = answer
            wall_s = time.perf_counter()
            if ok and frame is not None:
                return _Read(frame, pos_ms, wall_s)
            if self.file:
                return _Read(end="end of stream")
            if wall_s >= deadline:
                log.warning("%s: %s", self.label, stopped)
                return _Read(end=stopped)
            time.sleep(READ_RETRY_S)

    def _size_parameter(self) -> str:
        """The calibration's size parameter, named as the user wrote it."""
        if self._calib == "config dataset.camera":
            return "dataset.camera.width x dataset.camera.height"
        return f"Camera.width x Camera.height of {self._calib} (dataset.settings)"
