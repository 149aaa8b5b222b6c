"""Loading images and depth maps with clear errors, shared by every dataset reader."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from slamkit.errors import CalibrationError, DatasetError, FrameReadError

U8 = NDArray[np.uint8]
F32 = NDArray[np.float32]


@dataclass(frozen=True)
class LoadedImage:
    """grey: (H, W) uint8; color: (H, W, 3) uint8 BGR when the file has colour, else None."""

    grey: U8
    color: U8 | None


#: JPEG's end-of-image marker (EOI); a file cut short lacks it
_JPEG_EOI = b"\xff\xd9"
#: bytes at a JPEG's end searched for EOI (some writers pad after it)
_JPEG_TAIL_BYTES = 64


def jpeg_is_truncated(path: Path) -> bool:
    """True when a JPEG file lacks its end-of-image marker: OpenCV decodes such a file without an error (libjpeg
    fills the missing rows with grey and only warns on stderr), so the damage has to be looked for."""
    with path.open("rb") as f:
        f.seek(0, 2)
        size = f.tell()
        f.seek(max(0, size - _JPEG_TAIL_BYTES))
        tail = f.read()
    return _JPEG_EOI not in tail


def _imread(path: Path, flags: int) -> NDArray[np.generic]:
    if not path.is_file():
        raise FrameReadError(f"image file {path} does not exist")
    if path.suffix.lower() in (".jpg", ".jpeg") and jpeg_is_truncated(path):
        raise FrameReadError(f"image file {path} is damaged: a JPEG without its end marker (truncated)")
    image = cv2.imread(str(path), flags)
    if image is None:
        # OpenCV returns None for unreadable, truncated (PNG), or non-image files.
        raise FrameReadError(f"image file {path} could not be decoded (unreadable, truncated, or not an image)")
    return image


def check_size(
    path: Path, width: int, height: int, expected: tuple[int, int] | None, calib: str, what: str = "image file"
) -> None:
    """Raise CalibrationError when an image of ``width`` x ``height`` disagrees with ``expected`` (W, H).

    calib: where the expected size came from (a file or config key), for the message; what: what ``path`` is.
    """
    if expected is not None and (width, height) != (int(expected[0]), int(expected[1])):
        raise CalibrationError(
            f"{what} {path} is {width}x{height} px but the calibration ({calib}) is "
            f"{int(expected[0])}x{int(expected[1])} px"
        )


def load_image(
    path: Path, expected_size: tuple[int, int] | None = None, calib: str = "", keep_color: bool = True
) -> LoadedImage:
    """Read an 8-bit image as grey (and BGR colour when it has 3 or 4 channels and ``keep_color``).

    expected_size: (W, H) px of the calibration; a mismatch raises CalibrationError naming the file.
    """
    raw = _imread(path, cv2.IMREAD_UNCHANGED)
    if raw.dtype != np.uint8:
        raise DatasetError(f"image file {path} has pixel type {raw.dtype}; expected 8-bit (uint8)")
    color: U8 | None = None
    if raw.ndim == 2:
        grey = np.ascontiguousarray(raw, dtype=np.uint8)
    elif raw.ndim == 3 and raw.shape[2] in (3, 4):
        bgr = raw[:, :, :3] if raw.shape[2] == 4 else raw
        grey = np.asarray(cv2.cvtColor(np.ascontiguousarray(bgr), cv2.COLOR_BGR2GRAY), dtype=np.uint8)
        color = np.ascontiguousarray(bgr, dtype=np.uint8) if keep_color else None
    elif raw.ndim == 3 and raw.shape[2] == 1:
        grey = np.ascontiguousarray(raw[:, :, 0], dtype=np.uint8)
    else:
        raise DatasetError(f"image file {path} has shape {raw.shape}; expected a grey or BGR image")
    check_size(path, grey.shape[1], grey.shape[0], expected_size, calib)
    return LoadedImage(grey, color)


def image_size(path: Path) -> tuple[int, int]:
    """(W, H) px of an image file (decodes it; raises DatasetError when unreadable)."""
    raw = _imread(path, cv2.IMREAD_UNCHANGED)
    return int(raw.shape[1]), int(raw.shape[0])


def load_depth(path: Path, scale: float, expected_size: tuple[int, int] | None = None, calib: str = "") -> F32:
    """Read a 16-bit depth PNG -> (H, W) float32 metres (value / ``scale``; 0 stays 0 = unknown).

    scale: raw units per metre (TUM: 5000, ORB-SLAM's ``DepthMapFactor``).
    """
    raw = _imread(path, cv2.IMREAD_UNCHANGED)
    if raw.ndim != 2 or raw.dtype not in (np.uint16, np.float32):
        raise DatasetError(
            f"depth file {path} has shape {raw.shape} and type {raw.dtype}; expected a one-channel "
            "16-bit (or float32) depth image"
        )
    check_size(path, raw.shape[1], raw.shape[0], expected_size, calib, "depth file")
    return (raw.astype(np.float32) / np.float32(scale)).astype(np.float32)
