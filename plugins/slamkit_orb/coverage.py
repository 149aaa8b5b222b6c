"""Spatial coverage of keypoints: the share of the cells of a regular image grid that hold a keypoint."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

#: The grid the benchmark and tests report coverage on: 16 columns x 12 rows (40 x 40 px cells at 640x480).
DEFAULT_GRID = (16, 12)


def grid_coverage(uv_px: NDArray[np.floating], width: int, height: int, grid: tuple[int, int] = DEFAULT_GRID) -> float:
    """uv_px: (N, 2) keypoints in level-0 px of a (width, height) image; grid: (columns, rows).

    Returns the fraction in [0, 1] of the columns x rows equal cells that contain at least one keypoint.
    """
    n_cols, n_rows = grid
    if n_cols < 1 or n_rows < 1 or width < 1 or height < 1:
        raise ValueError(f"grid_coverage: grid {grid} and image size {width}x{height} must be positive")
    uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
    col = np.minimum((uv[inside, 0] * n_cols / width).astype(np.int64), n_cols - 1)
    row = np.minimum((uv[inside, 1] * n_rows / height).astype(np.int64), n_rows - 1)
    return float(np.unique(row * n_cols + col).size / (n_cols * n_rows))
