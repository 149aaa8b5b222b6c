"""FAST corners of one pyramid level with ORB-SLAM's per-cell two-threshold scheme.

ORB-SLAM (``ComputeKeyPointsOctTree``) tiles the level's detection area with cells of about 30 px, runs
FAST-9 with non-maximum suppression on each cell at the initial threshold (20) and, in a cell where that
finds nothing, again at the minimum threshold (7), so weakly textured cells still contribute corners.

Here FAST runs on whole areas and the cells are selected afterwards: a cell holding a corner with score >=
the initial threshold keeps only those corners, any other cell keeps all of its corners at the minimum
threshold. This equals the per-cell scheme because OpenCV's FAST score (the largest threshold at which the
point is still a corner) does not depend on the threshold FAST is run with, and a point is a corner at
threshold t exactly when its score is >= t. Non-maximum suppression keeps a corner whose score beats that
of every neighbouring corner; a neighbour that is a corner only at the low threshold has a score below the
initial threshold, so it can never suppress a corner scoring at or above it. Hence {low-threshold survivors
with score >= t_ini} = {survivors of a run at t_ini} (tests/unit/orb/test_grid_fast.py checks this on real
and synthetic images). The one difference is at cell borders: ORB-SLAM's per-cell runs cannot see a
neighbour across the border, so two adjacent corners in different cells may both survive there, while a
run over the whole area keeps only the stronger: the cleaner non-maximum suppression.

FAST itself runs with one of two backends giving identical corners, scores and order (tests/unit/orb/
test_fast9.py): "compiled", fast9.py's numba detector (default: several times faster, no Python object per
corner, no GIL held), or "opencv", cv2.FastFeatureDetector.

Two strategies give that same result (the test checks they agree bit for bit), and the extractor picks the
cheaper one per level from the previous frame:
- "whole": one FAST run at the minimum threshold over the whole area, then the selection above. Best when
  many cells are weak (real images with plain walls, sky, road).
- "cells": one run at the initial threshold over the whole area, then a run at the minimum threshold only
  on each weak cell, widened by 4 px so that every corner inside the cell sees the same neighbours as in a
  whole-area run (FAST reads 3 px around a pixel, non-maximum suppression 1 px more). Best on densely
  textured images, where the low threshold fires everywhere and few cells are weak.
With the compiled backend a FAST run costs the same at any threshold (it scores every pixel), so "auto"
always takes "whole" there.
"""

from __future__ import annotations

import math
import operator
import threading
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

# FAST-9/16 reads a Bresenham circle of radius 3 and detects nothing within FAST_RADIUS px of the border.
from slamkit_orb.fast9 import FAST_RADIUS, fast9_corners

#: A weak cell is re-run on itself widened by this much: FAST's radius plus non-maximum suppression's 1 px.
_CELL_MARGIN = FAST_RADIUS + 1
#: "auto" (opencv backend) runs the weak cells one by one when at most this share of the cells was weak.
SPARSE_WEAK_SHARE = 0.2

Strategy = Literal["auto", "whole", "cells"]
FastBackend = Literal["compiled", "opencv"]
FAST_BACKENDS: tuple[FastBackend, ...] = ("compiled", "opencv")
_RESPONSE = operator.attrgetter("response")


@dataclass(frozen=True)
class LevelCorners:
    """FAST corners of one level, in that level's pixels, in raster order (row, then column).

    xy: (N, 2) int32, corner column/row in the level image.
    response: (N,) float32, FAST score.
    region: (x0, y0, x1, y1) px, ORB-SLAM's distribution area (minBorderX, minBorderY, maxBorderX, maxBorderY):
        the detection area widened by the FAST radius; corners lie in [x0 + 3, x1 - 3) x [y0 + 3, y1 - 3).
    weak_share: share of the grid cells without a corner at the initial threshold (1.0 if none was run).
    """

    xy: NDArray[np.int32]
    response: NDArray[np.float32]
    region: tuple[int, int, int, int]
    weak_share: float


@dataclass(frozen=True)
class _Grid:
    """ORB-SLAM's cells on one level: n_cols x n_rows cells of w_cell x h_cell px from (edge, edge)."""

    edge: int
    n_cols: int
    n_rows: int
    w_cell: int
    h_cell: int

    def cell_of(self, xy: NDArray[np.int32]) -> NDArray[np.int64]:
        col = (xy[:, 0].astype(np.int64) - self.edge) // self.w_cell
        row = (xy[:, 1].astype(np.int64) - self.edge) // self.h_cell
        return row * self.n_cols + col


class GridFast:
    """ORB-SLAM's cell-wise FAST with an initial and a fallback threshold (see the module docstring).

    edge_threshold: px, no corner closer than this to the level border (ORB-SLAM's EDGE_THRESHOLD, 19).
    cell_size_px: nominal cell side (ORB-SLAM's W, 30); cells are stretched to tile the detection area.
    ini_threshold / min_threshold: FAST thresholds, grey levels (ORB-SLAM: 20 and 7).
    backend: FAST implementation, "compiled" (fast9.py) or "opencv" (cv2.FastFeatureDetector): same output.
    """

    def __init__(
        self,
        edge_threshold: int,
        cell_size_px: int,
        ini_threshold: int,
        min_threshold: int,
        backend: FastBackend = "compiled",
    ) -> None:
        if backend not in FAST_BACKENDS:
            raise ValueError(f"GridFast: backend must be one of {FAST_BACKENDS}, got {backend!r}")
        self.backend: FastBackend = backend
        self.edge_threshold = int(edge_threshold)
        self.cell_size_px = int(cell_size_px)
        self.ini_threshold = int(ini_threshold)
        self.min_threshold = int(min_threshold)
        # Detectors per thread: levels are processed concurrently and OpenCV does not promise that one
        # detector object may serve several threads at once.
        self._local = threading.local()

    def _detector(self, threshold: int) -> cv2.FastFeatureDetector:
        detectors: dict[int, cv2.FastFeatureDetector] | None = getattr(self._local, "fast", None)
        if detectors is None:
            detectors = self._local.fast = {}
        if threshold not in detectors:
            detectors[threshold] = cv2.FastFeatureDetector.create(
                threshold=threshold, nonmaxSuppression=True, type=cv2.FAST_FEATURE_DETECTOR_TYPE_9_16
            )
        return detectors[threshold]

    def _fast(
        self, image: NDArray[np.uint8], threshold: int, x0: int, y0: int, x1: int, y1: int
    ) -> tuple[NDArray[np.int32], NDArray[np.float32]]:
        """FAST with non-maximum suppression on image[y0:y1, x0:x1] -> (N, 2) int32 image px, (N,) scores."""
        if self.backend == "compiled":
            return fast9_corners(image, threshold, (x0, y0, x1, y1))
        keypoints = self._detector(threshold).detect(image[y0:y1, x0:x1])
        if not keypoints:
            return np.zeros((0, 2), np.int32), np.zeros(0, np.float32)
        xy = np.rint(cv2.KeyPoint.convert(keypoints)).astype(np.int32) + np.array([x0, y0], np.int32)
        response = np.fromiter(map(_RESPONSE, keypoints), dtype=np.float32, count=len(keypoints))
        return xy, response

    def region(self, width: int, height: int) -> tuple[int, int, int, int]:
        """ORB-SLAM's (minBorderX, minBorderY, maxBorderX, maxBorderY) for a (width, height) level."""
        lo = self.edge_threshold - FAST_RADIUS
        return lo, lo, width - lo, height - lo

    def cells(self, x0: int, y0: int, x1: int, y1: int) -> _Grid:
        """The grid of cells over the distribution area (x0, y0, x1, y1) (see ``region``)."""
        # ORB-SLAM's grid: nCols = floor(width / W) cells of ceil(width / nCols) px (at least one cell, where
        # ORB-SLAM would divide by zero on a level narrower than W); cell (i, j) detects in
        # [edge + j * wCell, edge + (j + 1) * wCell) horizontally, likewise vertically.
        width, height = x1 - x0, y1 - y0
        n_cols = max(1, int(width / self.cell_size_px))
        n_rows = max(1, int(height / self.cell_size_px))
        return _Grid(self.edge_threshold, n_cols, n_rows, math.ceil(width / n_cols), math.ceil(height / n_rows))

    def detect(
        self, level_image: NDArray[np.uint8], strategy: Strategy = "whole", weak_hint: float = 1.0
    ) -> LevelCorners:
        """level_image: (h, w) uint8 -> the corners ORB-SLAM's grid keeps on it (none if the level is too small).

        strategy: "whole" or "cells" (same result, see the module docstring), or "auto": with the opencv
        backend "cells" when ``weak_hint`` (the share of weak cells expected, e.g. from the previous frame) is
        at most SPARSE_WEAK_SHARE, else "whole"; always "whole" with the compiled backend.
        """
        h, w = level_image.shape
        x0, y0, x1, y1 = self.region(w, h)
        region = (x0, y0, x1, y1)
        if x1 - x0 <= 2 * FAST_RADIUS or y1 - y0 <= 2 * FAST_RADIUS:
            return LevelCorners(np.zeros((0, 2), np.int32), np.zeros(0, np.float32), region, 1.0)
        grid = self.cells(x0, y0, x1, y1)
        n_cells = grid.n_rows * grid.n_cols
        if strategy == "auto":
            sparse = self.backend == "opencv" and weak_hint <= SPARSE_WEAK_SHARE
            strategy = "cells" if sparse else "whole"
        if strategy == "whole" or self.min_threshold == self.ini_threshold:
            xy, response = self._fast(level_image, self.min_threshold, x0, y0, x1, y1)
            cell = grid.cell_of(xy)
            strong = response >= self.ini_threshold
            has_strong = np.zeros(n_cells, dtype=bool)
            has_strong[cell[strong]] = True
            keep = strong | ~has_strong[cell]
            weak_share = 1.0 - np.count_nonzero(has_strong) / n_cells
            return LevelCorners(xy[keep], response[keep], region, weak_share)

        xy, response = self._fast(level_image, self.ini_threshold, x0, y0, x1, y1)
        has_strong = np.zeros(n_cells, dtype=bool)
        has_strong[grid.cell_of(xy)] = True
        weak = np.flatnonzero(~has_strong)
        xy_parts, response_parts = [xy], [response]
        for c in weak.tolist():
            row, col = divmod(c, grid.n_cols)
            cx0 = grid.edge + col * grid.w_cell
            cy0 = grid.edge + row * grid.h_cell
            cx1 = min(cx0 + grid.w_cell, x1 - FAST_RADIUS)
            cy1 = min(cy0 + grid.h_cell, y1 - FAST_RADIUS)
            if cx0 >= cx1 or cy0 >= cy1:
                continue
            sub_x0, sub_y0 = max(x0, cx0 - _CELL_MARGIN), max(y0, cy0 - _CELL_MARGIN)
            sub_x1, sub_y1 = min(x1, cx1 + _CELL_MARGIN), min(y1, cy1 + _CELL_MARGIN)
            cxy, cresponse = self._fast(level_image, self.min_threshold, sub_x0, sub_y0, sub_x1, sub_y1)
            inside = (cxy[:, 0] >= cx0) & (cxy[:, 0] < cx1) & (cxy[:, 1] >= cy0) & (cxy[:, 1] < cy1)
            xy_parts.append(cxy[inside])
            response_parts.append(cresponse[inside])
        if len(xy_parts) > 1:
            xy, response = np.concatenate(xy_parts), np.concatenate(response_parts)
            # Raster order, as a whole-area FAST run returns them (the key is unique: columns < 2^31).
            order = np.argsort((xy[:, 1].astype(np.int64) << 31) + xy[:, 0], kind="stable")
            xy, response = xy[order], response[order]
        return LevelCorners(xy, response, region, weak.size / n_cells)
