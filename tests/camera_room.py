"""The synthetic room written as an MJPG .avi, which ``dataset=camera`` opens as a live stream (cv2.VideoCapture opens
a file path the way it opens a URL): the camera dataset's and the live runner's tests, without a camera."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from slamkit.io.synthetic.dataset import SyntheticDataset


def write_room_video(path: Path, n_frames: int, fps: float) -> dict[str, Any]:
    """The room's first ``n_frames`` frames (seed 0, as the default config renders them) as an MJPG .avi stamped at
    ``fps`` Hz; returns the room camera as a ``dataset.camera`` mapping (pinhole, no distortion)."""
    room = SyntheticDataset(scene="room", seed=0, max_frames=n_frames, imu=False, depth=False)
    cam = room.camera
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), fps, (cam.width, cam.height))
    assert writer.isOpened(), f"cannot write {path}"
    for frame in room:
        writer.write(np.asarray(cv2.cvtColor(frame.image, cv2.COLOR_GRAY2BGR)))
    writer.release()
    K = np.asarray(cam.K)
    return {"fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2])}


def camera_override(camera: dict[str, Any]) -> str:
    """``dataset.camera={fx: ..., ...}`` for a command line or compose_config."""
    return "dataset.camera={" + ", ".join(f"{k}: {v!r}" for k, v in camera.items()) + "}"
