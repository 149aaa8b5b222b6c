"""A frame the dataset cannot read (missing, undecodable, truncated JPEG) is skipped and reported, or stops the run
(``runner.bad_frames``); a truncated JPEG, which OpenCV decodes half grey without an error, is detected."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from slamkit.errors import ConfigError, FrameReadError
from slamkit.io.folder import FolderDataset
from slamkit.io.images import jpeg_is_truncated, load_image
from slamkit.runtime.source import readable_frames


def _jpeg(path: Path, seed: int = 0) -> Path:
    image = np.random.default_rng(seed).integers(0, 255, (48, 64), dtype=np.uint8)
    assert cv2.imwrite(str(path), image)
    return path


def test_a_truncated_jpeg_is_damaged_though_opencv_decodes_it(tmp_path: Path) -> None:
    good = _jpeg(tmp_path / "good.jpg")
    cut = tmp_path / "cut.jpg"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size * 2 // 3])
    assert cv2.imread(str(cut), cv2.IMREAD_GRAYSCALE) is not None  # why the check exists
    assert not jpeg_is_truncated(good) and jpeg_is_truncated(cut)
    assert load_image(good).grey.shape == (48, 64)
    with pytest.raises(FrameReadError, match=r"cut\.jpg is damaged: a JPEG without its end marker"):
        load_image(cut)
    with pytest.raises(FrameReadError, match=r"gone\.jpg does not exist"):
        load_image(tmp_path / "gone.jpg")


def _folder(tmp_path: Path, n: int = 6) -> FolderDataset:
    images = tmp_path / "images"
    images.mkdir()
    for i in range(n):
        _jpeg(images / f"{i:03d}.jpg", seed=i)
    return FolderDataset(root=images, fps=10.0, camera={"fx": 50.0, "fy": 50.0, "cx": 32.0, "cy": 24.0})


def test_skip_leaves_out_the_unreadable_frames_and_reports_them(tmp_path: Path) -> None:
    dataset = _folder(tmp_path)
    damaged = tmp_path / "images" / "002.jpg"
    damaged.write_bytes(damaged.read_bytes()[:100])
    (tmp_path / "images" / "004.jpg").write_bytes(b"not an image")
    reported: list[tuple[int, str]] = []
    frames = list(readable_frames(dataset, "skip", lambda i, why: reported.append((i, why))))
    assert [f.index for f in frames] == [0, 1, 3, 5]  # the others keep their numbers
    assert [i for i, _ in reported] == [2, 4]
    assert "002.jpg is damaged" in reported[0][1] and "004.jpg" in reported[1][1]


def test_stop_ends_the_sequence_at_the_unreadable_frame(tmp_path: Path) -> None:
    dataset = _folder(tmp_path)
    (tmp_path / "images" / "003.jpg").write_bytes(b"not an image")
    seen = []
    with pytest.raises(FrameReadError, match=r"003\.jpg"):
        for frame in readable_frames(dataset, "stop"):
            seen.append(frame.index)
    assert seen == [0, 1, 2]
    with pytest.raises(ConfigError, match=r"runner\.bad_frames = 'ignore'"):
        readable_frames(dataset, "ignore")
