"""A folder of images (sorted by file name) as a monocular sequence.

Times are ``k / fps``, or, with ``timestamps_from_names``, the numeric file names times
``name_time_scale`` (1 for names in seconds like TUM's, 1e-9 for EuRoC's nanosecond names). The camera
comes from ``camera: {model, fx, fy, cx, cy, dist | k[, width, height]}`` or ``settings: PATH``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slamkit.errors import ConfigError
from slamkit.io.base import SequenceDataset
from slamkit.io.calibration import camera_from_options, load_settings, orb_extractor_from_options
from slamkit.io.images import image_size, load_image
from slamkit.io.textfiles import IMAGE_SUFFIXES, list_images, require_dir, times_from_names
from slamkit.sensors import FrameData

F64 = NDArray[np.float64]


class FolderDataset(SequenceDataset):
    """Images of one folder, grey + colour when the files have colour; no depth or ground truth.

    Constructor keywords are the keys of conf/dataset/folder.yaml:
    root: the folder. fps: frame rate (Hz); required unless timestamps_from_names (then it defaults to
    the median rate of the names). timestamps_from_names: take times from numeric file names.
    name_time_scale: seconds per unit of a name. camera: camera mapping (see camera_from_config).
    settings: ORB-SLAM settings file, instead of ``camera``. extensions: image file suffixes to read.
    """

    def __init__(
        self,
        root: str | Path,
        skip: Sequence[int] | None = None,
        max_frames: int | None = None,
        fps: float | None = None,
        timestamps_from_names: bool = False,
        name_time_scale: float = 1.0,
        camera: Mapping[str, Any] | None = None,
        settings: str | Path | None = None,
        extensions: Sequence[str] | None = None,
    ) -> None:
        self.root = require_dir(Path(root), "image folder (dataset.root)")
        self.name = f"folder:{self.root.name}"
        suffixes = tuple(extensions) if extensions else IMAGE_SUFFIXES
        self._files = list_images(self.root, suffixes, what="image folder (dataset.root)")
        if fps is not None and float(fps) <= 0:
            raise ConfigError(f"dataset.fps must be positive, got {fps}")
        if timestamps_from_names:
            self._t_s: F64 = times_from_names(self._files, float(name_time_scale), what="dataset.timestamps_from_names")
            if fps is None:
                steps = np.diff(self._t_s)
                fps = 1.0 / float(np.median(steps)) if steps.size else 30.0
        else:
            if fps is None:
                raise ConfigError(
                    f"dataset.fps is required for the image folder {self.root} (or set "
                    "dataset.timestamps_from_names: true)"
                )
            self._t_s = np.arange(len(self._files), dtype=np.float64) / float(fps)
        self.fps = float(fps)

        first_size = image_size(self._files[0])
        loaded = load_settings(settings, first_size)
        self.orb_settings = orb_extractor_from_options(None, loaded)
        self.camera, self._calib = camera_from_options(camera, loaded, first_size)
        self._setup_selection(skip, max_frames)

    def _n_raw(self) -> int:
        return len(self._files)

    def timestamps(self) -> F64:
        """(N,) s times of the yielded frames."""
        return self._t_s[self.raw_indices()]

    def _load(self, raw_index: int, out_index: int) -> FrameData:
        path = self._files[raw_index]
        image = load_image(path, (self.camera.width, self.camera.height), self._calib)
        return FrameData(
            index=out_index,
            timestamp_s=float(self._t_s[raw_index]),
            image=image.grey,
            color=image.color,
            source=str(path),
        )
