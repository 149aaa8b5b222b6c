"""Shared machinery of every dataset: frame indexing, the ``skip`` span, and ``max_frames``."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterator, Sequence

import numpy as np
from numpy.typing import NDArray

from slamkit.errors import ConfigError, DatasetError, FrameReadError
from slamkit.interfaces import Camera
from slamkit.io.orbslam_settings import OrbExtractorSettings
from slamkit.sensors import FrameData, Trajectory


def resolve_skip(skip: Sequence[int] | None, n_frames: int) -> tuple[int, int] | None:
    """Validate ``dataset.skip=[FIRST, LAST]`` (inclusive, 0-based raw frame numbers).

    Returns the span or None. Raises ConfigError naming ``dataset.skip`` when it is malformed.
    """
    if skip is None or len(skip) == 0:
        return None
    if len(skip) != 2:
        raise ConfigError(f"dataset.skip must be [FIRST, LAST] (two frame numbers), got {list(skip)}")
    first, last = int(skip[0]), int(skip[1])
    if first < 0 or last < first:
        raise ConfigError(f"dataset.skip=[{first}, {last}]: expected 0 <= FIRST <= LAST")
    if first >= n_frames:
        raise ConfigError(f"dataset.skip=[{first}, {last}]: FIRST is past the sequence's {n_frames} frames")
    return first, last


class SequenceDataset(ABC):
    """Base class of datasets made of N raw frames addressed by number.

    Subclasses fill ``name``, ``camera`` (and the optional stereo/IMU fields), implement ``_n_raw`` and
    ``_load(raw_index, out_index)``, and call ``_setup_selection(skip, max_frames)`` at the end of their
    constructor. The base class applies ``skip`` (a span of raw frames dropped, as if the camera were
    kidnapped) and ``max_frames`` (the sequence is cut after that many yielded frames).
    """

    name: str
    camera: Camera
    camera_right: Camera | None = None
    T_l_r: NDArray[np.float64] | None = None
    T_b_c: NDArray[np.float64] | None = None
    fps: float = 30.0
    ground_truth: Trajectory | None = None
    #: ORB-SLAM's extractor settings for this camera (settings file or ``dataset.orb_extractor``), None: no opinion
    orb_settings: OrbExtractorSettings | None = None
    _selected: NDArray[np.int64]

    @abstractmethod
    def _n_raw(self) -> int:
        """Number of raw frames in the sequence (before skip / max_frames)."""

    @abstractmethod
    def _load(self, raw_index: int, out_index: int) -> FrameData:
        """Read raw frame ``raw_index`` and return it as the ``out_index``-th yielded frame."""

    def _setup_selection(self, skip: Sequence[int] | None, max_frames: int | None) -> None:
        n = self._n_raw()
        selected = np.arange(n, dtype=np.int64)
        span = resolve_skip(skip, n)
        if span is not None:
            selected = selected[(selected < span[0]) | (selected > span[1])]
        if max_frames is not None:
            if int(max_frames) <= 0:
                raise ConfigError(f"dataset.max_frames must be a positive integer or null, got {max_frames}")
            selected = selected[: int(max_frames)]
        self._selected = selected

    def raw_indices(self) -> NDArray[np.int64]:
        """(N,) the raw frame numbers this dataset yields, in order."""
        return self._selected

    def __len__(self) -> int:
        return int(self._selected.shape[0])

    def __getitem__(self, i: int) -> FrameData:
        if not 0 <= i < len(self):
            raise IndexError(f"{self.name}: frame {i} out of range [0, {len(self)})")
        try:
            return self._load(int(self._selected[i]), i)
        except FrameReadError:
            raise  # a missing or unreadable file: the runner skips the frame or stops (runner.bad_frames)
        except DatasetError as exc:
            # a file of this frame the run cannot use (a depth map or right image of another size than the
            # calibration's): the message names the file; say which frame too
            raise type(exc)(f"frame {i}: {exc}") from exc

    def __iter__(self) -> Iterator[FrameData]:
        for i in range(len(self)):
            yield self[i]
