"""dataset=camera (slamkit/io/camera.py): a video file opened as a live stream, the stream clock, the ends of a
stream (file end, duration, frame count, a read that times out), and the errors a user meets (a device that does
not open, a calibration of another size, bad values)."""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from omegaconf import OmegaConf

import slamkit.io.camera as camera_module
from slamkit.errors import CalibrationError, ConfigError, DatasetError
from slamkit.interfaces import Dataset
from slamkit.io.camera import CameraDataset, StreamClock, parse_device
from slamkit.runtime.source import frame_count, is_live

CONF = Path(__file__).resolve().parents[3] / "conf" / "dataset" / "camera.yaml"
CAMERA = {"fx": 100.0, "fy": 100.0, "cx": 79.5, "cy": 59.5}
W, H = 160, 120


@pytest.fixture(scope="module")
def clip(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """12 textured frames at 30 Hz, MJPG."""
    path = tmp_path_factory.mktemp("camera") / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 30.0, (W, H))
    for i in range(12):
        writer.write(np.random.default_rng(i).integers(0, 256, (H, W, 3), dtype=np.uint8))
    writer.release()
    return path


def test_a_video_file_is_a_live_paced_stream_stamped_by_the_capture(clip: Path) -> None:
    ds = CameraDataset(device=str(clip), camera=CAMERA)
    assert isinstance(ds, Dataset) and is_live(ds) and frame_count(ds) is None
    with pytest.raises(TypeError, match="live source: it has no length"):
        len(ds)
    assert ds.paced and ds.fps == 30.0 and ds.ground_truth is None and (ds.camera.width, ds.camera.height) == (W, H)
    frames = list(ds)
    assert [f.index for f in frames] == list(range(12)) and ds.end_reason == "end of stream"
    # CAP_PROP_POS_MSEC of a 30 Hz file: k / 30 s
    assert np.allclose([f.timestamp_s for f in frames], np.arange(12) / 30.0, atol=1e-6)
    assert frames[0].color is not None and frames[0].image.shape == (H, W)
    assert len(list(ds)) == 12  # a second pass opens the file again


def test_the_run_ends_on_duration_or_frame_count(clip: Path) -> None:
    ds = CameraDataset(device=str(clip), camera=CAMERA, duration_s=0.2)
    assert len(list(ds)) == 6 and ds.end_reason is not None and "dataset.duration_s=0.2" in ds.end_reason
    ds = CameraDataset(device=str(clip), camera=CAMERA, max_frames=4)
    assert len(list(ds)) == 4 and ds.end_reason is not None and "dataset.max_frames=4" in ds.end_reason


def test_stream_clock_uses_the_capture_while_it_increases_then_the_wall_clock(caplog: Any) -> None:
    clock = StreamClock(opened_at_s=100.0, label="cam")
    with caplog.at_level(logging.INFO, logger="slamkit.io"):
        assert clock.stamp(0.0, 100.5) == 0.0 and clock.kind == StreamClock.CAPTURE
        assert clock.stamp(40.0, 100.6) == pytest.approx(0.04)
        # the backend's clock stalls: wall clock from the last stamp on, still increasing
        assert clock.stamp(40.0, 100.7) == pytest.approx(0.14) and clock.kind == StreamClock.WALL
        assert clock.stamp(80.0, 100.8) == pytest.approx(0.24)  # never back to the capture's
    assert "from the capture's" in caplog.text and "not increasing" in caplog.text
    wall = StreamClock(opened_at_s=10.0, label="cam")
    assert wall.stamp(-1.0, 10.25) == pytest.approx(0.25) and wall.kind == StreamClock.WALL
    assert wall.stamp(math.nan, 10.30) == pytest.approx(0.30)


class _StallingCapture:
    """A device that delivers ``n`` frames, then blocks in read() (a stream that stopped mid-read)."""

    def __init__(self, n: int) -> None:
        self.n, self.reads = n, 0

    def isOpened(self) -> bool:
        return True

    def read(self) -> tuple[bool, Any]:
        self.reads += 1
        if self.reads > self.n:
            time.sleep(30.0)
        return True, np.full((H, W, 3), self.reads, np.uint8)

    def get(self, prop: int) -> float:
        return -1.0  # no capture clock, no frame rate

    def set(self, prop: int, value: float) -> bool:
        return False

    def release(self) -> None:
        pass


def test_a_stream_that_stops_mid_read_ends_after_the_read_timeout(monkeypatch: Any, caplog: Any) -> None:
    monkeypatch.setattr(camera_module, "open_capture", lambda *args, **kwargs: _StallingCapture(6))
    ds = CameraDataset(device=0, camera=CAMERA, read_timeout_s=0.3)
    assert not ds.paced and ds.fps == 30.0  # a device paces itself; no rate stated: fallback_fps
    t0 = time.perf_counter()
    with caplog.at_level(logging.WARNING, logger="slamkit.io"):
        frames = list(ds)
    assert time.perf_counter() - t0 < 3.0  # the blocked read is abandoned, not waited for
    assert len(frames) == 5  # the first frame sized the calibration when the dataset was built
    assert ds.end_reason is not None and "no frame for 0.3 s (dataset.read_timeout_s)" in ds.end_reason
    assert "the stream stopped" in caplog.text
    t = [f.timestamp_s for f in frames]
    assert np.all(np.diff(t) > 0)  # wall clock since opening


def test_a_device_that_cannot_be_opened_is_one_error_naming_it() -> None:
    with pytest.raises(DatasetError, match=r"^camera device 63 \(dataset\.device\) could not be opened"):
        CameraDataset(device=63, camera=CAMERA)
    with pytest.raises(DatasetError, match=r"stream .*nowhere\.avi \(dataset\.device\) could not be opened"):
        CameraDataset(device="/nonexistent/nowhere.avi", camera=CAMERA)


def test_a_calibration_of_another_size_names_the_parameter(clip: Path) -> None:
    with pytest.raises(
        CalibrationError,
        match=r"clip\.avi \(dataset\.device\) delivers 160x120 px frames but dataset\.camera\.width x "
        r"dataset\.camera\.height is 320x240 px",
    ):
        CameraDataset(device=str(clip), camera={**CAMERA, "width": 320, "height": 240})


def test_bad_values_are_config_errors_naming_the_key(clip: Path) -> None:
    assert parse_device("2") == 2 and parse_device(" rtsp://h/s ") == "rtsp://h/s"
    for device in (-1, "", True, 1.5):
        with pytest.raises(ConfigError, match=r"dataset\.device"):
            parse_device(device)  # type: ignore[arg-type]
    for key, value in (("read_timeout_s", 0), ("duration_s", -1.0), ("fps", "x"), ("max_frames", 0)):
        with pytest.raises(ConfigError, match=rf"dataset\.{key}"):
            CameraDataset(device=str(clip), camera=CAMERA, **{key: value})
    with pytest.raises(ConfigError, match=r"dataset\.backend = 'nope'"):
        CameraDataset(device=str(clip), camera=CAMERA, backend="nope")


def test_config_node_keys_are_the_constructor_keywords_each_commented() -> None:
    import inspect

    cfg = OmegaConf.load(CONF)
    assert cfg._target_ == "slamkit.io.camera.CameraDataset"
    assert sorted(str(k) for k in cfg if k != "_target_") == sorted(inspect.signature(CameraDataset).parameters)
    for line in CONF.read_text().splitlines():
        if line and not line.startswith(("#", "_target_")):
            assert "#" in line, f"camera.yaml: option without a comment: {line}"


def test_export_does_not_open_a_live_source_again_for_colours() -> None:
    """slamkit export colours points from the run's images read again; a live device's frames now are not the run's."""
    from slamkit.errors import SlamkitError
    from slamkit.export.colours import dataset_for_colours

    with pytest.raises(SlamkitError, match="live source, whose frames were not stored"):
        dataset_for_colours({"dataset": {"_target_": "slamkit.io.camera.CameraDataset", "device": 63}})
