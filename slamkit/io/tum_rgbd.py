"""TUM RGB-D benchmark reader (Sturm et al., IROS 2012).

A sequence folder holds ``rgb.txt`` / ``depth.txt`` (``timestamp filename`` lists), ``rgb/`` and ``depth/``
PNGs (depth: 16-bit, 5000 units per metre), and ``groundtruth.txt`` (``t tx ty tz qx qy qz qw``, poses
T_w_c of the colour camera). What is done when parts are missing (trimmed copies of sequences exist):

- no ``rgb.txt``: the images of ``rgb/`` are used, sorted by name, with the time taken from the file name
  (TUM names are the timestamps, e.g. ``1305031102.175304.png``);
- no ``depth.txt``: likewise from ``depth/``; with neither (or ``use_depth: false``) frames have no depth;
- with depth, colour frames are paired with depth maps as TUM's associate.py does (greedy by time
  difference, < ``max_dt_s``); colour frames without a depth partner are dropped;
- no ``groundtruth.txt`` (and no ``groundtruth: PATH``): no ground truth.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slamkit.errors import CalibrationError, ConfigError, DatasetError
from slamkit.geometry.camera import PinholeCamera
from slamkit.io.base import SequenceDataset
from slamkit.io.calibration import load_settings, orb_extractor_from_options
from slamkit.io.ground_truth import poses_at
from slamkit.io.images import load_depth, load_image
from slamkit.io.textfiles import (
    StampedFiles,
    list_images,
    read_stamped_files,
    require_dir,
    require_file,
    times_from_names,
)
from slamkit.io.timing import associate_stamps
from slamkit.io.trajectory_io import read_tum_trajectory
from slamkit.sensors import FrameData

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

TUM_SIZE = (640, 480)
#: TUM's published colour-camera intrinsics (fx, fy, cx, cy, (k1, k2, p1, p2, k3)), from the dataset's
#: "file formats" page. fr3 images are already undistorted; "ros" is the ROS default the images were
#: registered with (fx = fy = 525, cx = 319.5, cy = 239.5).
TUM_INTRINSICS: dict[str, tuple[float, float, float, float, tuple[float, ...]]] = {
    "fr1": (517.3, 516.5, 318.6, 255.3, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "fr2": (520.9, 521.0, 325.1, 249.7, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "fr3": (535.4, 539.2, 320.1, 247.6, (0.0, 0.0, 0.0, 0.0, 0.0)),
    "ros": (525.0, 525.0, 319.5, 239.5, (0.0, 0.0, 0.0, 0.0, 0.0)),
}
#: TUM depth PNG units per metre.
TUM_DEPTH_SCALE = 5000.0

_FREIBURG = re.compile(r"(?:freiburg|fr)([123])(?![0-9])", re.IGNORECASE)


def detect_freiburg(root: Path) -> str | None:
    """'fr1' / 'fr2' / 'fr3' from a folder name like ``rgbd_dataset_freiburg1_xyz``, else None."""
    m = _FREIBURG.search(root.name)
    return f"fr{m.group(1)}" if m else None


def tum_camera(intrinsics: str) -> PinholeCamera:
    """The 640x480 colour camera of a TUM sensor: ``fr1`` | ``fr2`` | ``fr3`` | ``ros``."""
    if intrinsics not in TUM_INTRINSICS:
        raise ConfigError(f"dataset.intrinsics: expected one of {sorted(TUM_INTRINSICS)} or null, got {intrinsics!r}")
    fx, fy, cx, cy, dist = TUM_INTRINSICS[intrinsics]
    return PinholeCamera(TUM_SIZE[0], TUM_SIZE[1], fx, fy, cx, cy, dist=dist)


def _stamped_list(root: Path, kind: str) -> StampedFiles | None:
    """``kind``.txt when present, else the images of ``kind``/ timed by their names, else None."""
    list_file = root / f"{kind}.txt"
    if list_file.is_file():
        files = read_stamped_files(list_file, root, sep=None, ns_stamps=False, what=f"TUM {kind}.txt")
        files.check_files_exist()
        return files
    folder = root / kind
    if folder.is_dir():
        images = list_images(folder, suffixes=(".png",), what=f"TUM {kind}/")
        t_s = times_from_names(images, 1.0, what=f"TUM {kind}/ image")
        log.info("%s is absent: using the %d images of %s timed by their names", list_file, len(images), folder)
        return StampedFiles(folder, t_s, images, np.zeros(len(images), dtype=np.int64))
    return None


class TumRgbdDataset(SequenceDataset):
    """A TUM RGB-D sequence: grey + BGR colour images, depth in metres, ground truth T_w_c.

    Constructor keywords are the keys of conf/dataset/tum_rgbd.yaml:
    root: the sequence folder. intrinsics: 'fr1' | 'fr2' | 'fr3' | 'ros' | None (detected from the folder
    name). settings: an ORB-SLAM settings file whose camera (and DepthMapFactor) replace TUM's.
    orb_extractor: ORB-SLAM's extractor settings for the TUM cameras (``orb_settings``; the settings file's win).
    use_depth: read depth maps when the sequence has them (None: no; the app resolves the config's null from the
    front end). depth_scale: PNG units per metre (None: the
    settings' DepthMapFactor, else 5000). max_dt_s: colour-depth association tolerance (s).
    groundtruth: a TUM trajectory file replacing root/groundtruth.txt. gt_max_gap_s: interpolate the
    ground truth only between samples at most this far apart (s).
    """

    def __init__(
        self,
        root: str | Path,
        skip: Sequence[int] | None = None,
        max_frames: int | None = None,
        intrinsics: str | None = None,
        settings: str | Path | None = None,
        orb_extractor: Mapping[str, Any] | None = None,
        use_depth: bool | None = True,
        depth_scale: float | None = None,
        max_dt_s: float = 0.02,
        groundtruth: str | Path | None = None,
        gt_max_gap_s: float = 0.1,
    ) -> None:
        self.root = require_dir(Path(root), "TUM RGB-D sequence (dataset.root)")
        self.name = f"tum_rgbd:{self.root.name}"
        rgb = _stamped_list(self.root, "rgb")
        if rgb is None:
            raise DatasetError(f"TUM RGB-D sequence {self.root}: neither rgb.txt nor an rgb/ folder exists")
        use_depth = bool(use_depth)
        depth = _stamped_list(self.root, "depth") if use_depth else None
        if use_depth and depth is None:
            log.warning("%s has no depth.txt and no depth/ folder: frames carry no depth", self.root)

        if depth is not None:
            ia, ib = associate_stamps(rgb.t_s, depth.t_s, float(max_dt_s))
            if ia.size == 0:
                raise DatasetError(
                    f"{rgb.list_path} and {depth.list_path}: no colour/depth pair is closer than max_dt_s={max_dt_s} s"
                )
            self._depth_files: list[Path] | None = [depth.files[int(j)] for j in ib]
        else:
            ia = np.arange(len(rgb), dtype=np.int64)
            self._depth_files = None
        self._t_s: F64 = rgb.t_s[ia]
        self._rgb_files = [rgb.files[int(i)] for i in ia]

        loaded = load_settings(settings, TUM_SIZE)
        # the RGB-D front end's virtual baseline and close/far threshold, when the settings file gives them
        self.settings_bf: float | None = loaded.bf if loaded is not None else None
        self.settings_th_depth: float | None = loaded.th_depth if loaded is not None else None
        self.orb_settings = orb_extractor_from_options(orb_extractor, loaded)
        if loaded is not None:
            self.camera = loaded.camera
            self._calib = str(loaded.path)
            self.fps = loaded.fps or 30.0
        else:
            key = intrinsics if intrinsics is not None else detect_freiburg(self.root)
            if key is None:
                raise CalibrationError(
                    f"{self.root}: cannot tell the TUM sensor from the folder name (no 'freiburg1/2/3'); "
                    "set dataset.intrinsics to fr1, fr2, fr3 or ros, or dataset.settings"
                )
            self.camera = tum_camera(key)
            self._calib = f"TUM {key} intrinsics"
            self.fps = 30.0
        if depth_scale is not None:
            self.depth_scale = float(depth_scale)
        elif loaded is not None and loaded.depth_map_factor is not None:
            self.depth_scale = float(loaded.depth_map_factor)
        else:
            self.depth_scale = TUM_DEPTH_SCALE
        if self.depth_scale <= 0:
            raise ConfigError(f"dataset.depth_scale must be positive, got {self.depth_scale}")

        gt_path = Path(groundtruth) if groundtruth else self.root / "groundtruth.txt"
        if groundtruth:
            require_file(gt_path, "dataset.groundtruth")
        self.ground_truth = read_tum_trajectory(gt_path) if gt_path.is_file() else None
        self._gt = (
            poses_at(self.ground_truth, self._t_s, float(gt_max_gap_s))
            if self.ground_truth is not None
            else [None] * len(self._t_s)
        )
        self._setup_selection(skip, max_frames)

    def _n_raw(self) -> int:
        return int(self._t_s.shape[0])

    def timestamps(self) -> F64:
        """(N,) s capture times of the yielded frames."""
        return self._t_s[self.raw_indices()]

    def _load(self, raw_index: int, out_index: int) -> FrameData:
        size = (self.camera.width, self.camera.height)
        path = self._rgb_files[raw_index]
        image = load_image(path, size, self._calib)
        depth = None
        if self._depth_files is not None:
            depth = load_depth(self._depth_files[raw_index], self.depth_scale, size, self._calib)
        return FrameData(
            index=out_index,
            timestamp_s=float(self._t_s[raw_index]),
            image=image.grey,
            color=image.color,
            depth_m=depth,
            T_w_c_gt=self._gt[raw_index],
            source=str(path),
        )
