"""KITTI odometry reader (Geiger et al., CVPR 2012).

``root`` holds ``sequences/NN/`` (``image_0/`` left grey, ``image_1/`` right grey, ``calib.txt`` with the
rectified projection matrices ``P0: ...`` .. ``P3: ...``, ``times.txt``) and ``poses/NN.txt`` (ground truth
for 00-10: one row-major 3x4 T_w_c of camera 0 per frame, world = first camera frame).

Images are ``000000.png``, ``000001.png``, ... and frame k has time line k of times.txt. A sequence may
hold only the first images (trimmed copies): the frames are the images present, which must be
consecutive from 000000 and no more than times.txt has lines. The image size is not in calib.txt, so the
camera takes it from the first image (and every image must match it).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slamkit.errors import CalibrationError, DatasetError
from slamkit.geometry.camera import PinholeCamera
from slamkit.io.base import SequenceDataset
from slamkit.io.calibration import load_settings, orb_extractor_from_options
from slamkit.io.images import image_size, load_image
from slamkit.io.textfiles import (
    check_columns,
    list_images,
    parse_float,
    read_rows,
    require_dir,
)
from slamkit.io.trajectory_io import read_kitti_poses, read_times
from slamkit.sensors import FrameData

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: KITTI's nominal camera rate (Hz); times.txt shows ~9.65 Hz on average.
KITTI_FPS = 10.0


def read_kitti_calib(path: Path) -> dict[str, F64]:
    """calib.txt -> {'P0': (3, 4), ...} projection matrices (rectified, px). Needs P0 and P1."""
    what = "KITTI calib 'Pn: 12 numbers'"
    rows = read_rows(path, what=what)
    check_columns(path, rows, 13, what)
    out: dict[str, F64] = {}
    for row in rows:
        key = row.fields[0].rstrip(":")
        vals = np.array([parse_float(path, row, c, what) for c in range(1, 13)], dtype=np.float64)
        out[key] = vals.reshape(3, 4)
    for key in ("P0", "P1"):
        if key not in out:
            raise CalibrationError(f"{path}: missing the '{key}:' line (expected P0 and P1 projection matrices)")
    return out


def _frame_images(folder: Path, n_times: int, times_path: Path) -> list[Path]:
    images = list_images(folder, suffixes=(".png",), what=f"KITTI {folder.name}/")
    for k, img in enumerate(images):
        if img.name != f"{k:06d}.png":
            raise DatasetError(f"{folder}: expected image {k:06d}.png (consecutive frame numbers), found {img.name}")
    if len(images) > n_times:
        raise DatasetError(f"{folder}: {len(images)} images but {times_path} has only {n_times} times")
    if len(images) < n_times:
        log.info("%s: %d of %d frames have images; reading those", folder, len(images), n_times)
    return images


class KittiDataset(SequenceDataset):
    """A KITTI odometry sequence: grey left (and right) rectified images and camera-0 ground truth.

    Constructor keywords are the keys of conf/dataset/kitti.yaml:
    root: folder holding sequences/ and poses/. sequence: two-digit sequence name. stereo: also read
    image_1 (baseline from P1). settings: ORB-SLAM settings whose camera (and bf) replace calib.txt's.
    orb_extractor: ORB-SLAM's extractor settings for KITTI (``orb_settings``; the settings file's win).
    """

    def __init__(
        self,
        root: str | Path,
        sequence: str | int = "07",
        skip: Sequence[int] | None = None,
        max_frames: int | None = None,
        stereo: bool = False,
        settings: str | Path | None = None,
        orb_extractor: Mapping[str, Any] | None = None,
    ) -> None:
        self.root = require_dir(Path(root), "KITTI odometry root (dataset.root)")
        seq = f"{int(sequence):02d}" if str(sequence).isdigit() else str(sequence)
        self.sequence = seq
        self.seq_dir = require_dir(self.root / "sequences" / seq, f"KITTI sequence {seq}")
        self.name = f"kitti:{seq}"
        self.stereo = bool(stereo)

        times_path = self.seq_dir / "times.txt"
        t_all = read_times(times_path)
        self._files = _frame_images(self.seq_dir / "image_0", len(t_all), times_path)
        self._t_s: F64 = t_all[: len(self._files)].copy()
        self._right: list[Path] | None = None
        if self.stereo:
            right_dir = require_dir(self.seq_dir / "image_1", f"KITTI sequence {seq} right images (stereo)")
            self._right = [right_dir / f.name for f in self._files]
            for f in self._right:
                if not f.is_file():
                    raise DatasetError(
                        f"{right_dir}: right image {f.name} of left {f.parent.name}/{f.name} does not exist"
                    )

        calib_path = self.seq_dir / "calib.txt"
        P = read_kitti_calib(calib_path)
        first_size = image_size(self._files[0])
        P0, P1 = P["P0"], P["P1"]
        fx, fy, cx, cy = P0[0, 0], P0[1, 1], P0[0, 2], P0[1, 2]
        # Rectified pair: P_i = K [I | t_i] with t_i = -(baseline_i, 0, 0) * fx; camera 1 sits at +x.
        self.baseline_m = float((P0[0, 3] - P1[0, 3]) / P1[0, 0])
        self.camera = PinholeCamera(first_size[0], first_size[1], fx, fy, cx, cy)
        self._calib = f"{calib_path} (size of {self._files[0].name})"
        self.fps = KITTI_FPS
        loaded = load_settings(settings, first_size)
        self.orb_settings = orb_extractor_from_options(orb_extractor, loaded)
        if loaded is not None:
            self.camera = loaded.camera
            self._calib = str(loaded.path)
            self.fps = loaded.fps or KITTI_FPS
        if self.stereo:
            if loaded is not None:
                self.camera_right, self.T_l_r = loaded.stereo_pair()
                self.baseline_m = float(self.T_l_r[0, 3])
            else:
                self.camera_right = self.camera
                T_l_r = np.eye(4)
                T_l_r[0, 3] = self.baseline_m
                self.T_l_r = T_l_r

        poses_path = self.root / "poses" / f"{seq}.txt"
        self.ground_truth = read_kitti_poses(poses_path, times_path) if poses_path.is_file() else None
        self._setup_selection(skip, max_frames)

    def _n_raw(self) -> int:
        return len(self._files)

    def timestamps(self) -> F64:
        """(N,) s capture times of the yielded frames (times.txt, from the sequence start)."""
        return self._t_s[self.raw_indices()]

    def _load(self, raw_index: int, out_index: int) -> FrameData:
        path = self._files[raw_index]
        size = (self.camera.width, self.camera.height)
        grey = load_image(path, size, self._calib, keep_color=False).grey
        right = None
        if self._right is not None:
            right = load_image(self._right[raw_index], size, self._calib, keep_color=False).grey
        gt = None
        if self.ground_truth is not None:  # one pose per time, times cover every image
            gt = self.ground_truth.T_w_c[raw_index].copy()
        return FrameData(
            index=out_index,
            timestamp_s=float(self._t_s[raw_index]),
            image=grey,
            image_right=right,
            T_w_c_gt=gt,
            source=str(path),
        )
