"""One pyramid level's keypoints in a single compiled call: FAST, ORB-SLAM's cell selection, the quadtree and
the orientation, without the GIL.

The same steps as the extractor's Python path (grid_fast.GridFast.detect with the "whole" strategy, then
quadtree.distribute_quadtree and orientation.intensity_centroid_angles), with the glue between them compiled
too: the result is identical (tests/unit/orb/test_level_kernel.py), the difference is how often the thread
gives up and takes back the GIL. The Python path releases it at every kernel call and at every numpy operation
on a large array, about 140 times per 640x480 frame; while another thread runs Python code (local mapping),
each of those takes up to a GIL switch interval to come back, and a 6 ms extraction took 34 ms beside a thread
that only ran Python (benchmarks/extraction_gil.py). Here a level costs one release for these steps, and
``levels_keypoints`` does several levels in one call (the extractor makes one call per thread).
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

from slamkit_orb.fast9 import FAST_RADIUS, _fast9
from slamkit_orb.grid_fast import GridFast
from slamkit_orb.orientation import intensity_centroid_angles
from slamkit_orb.quadtree import distribute_quadtree


@njit(cache=True, nogil=True)
def _level_keypoints(  # pragma: no cover - compiled
    image: NDArray[np.uint8],
    min_threshold: int,
    ini_threshold: int,
    x0: int,
    y0: int,
    x1: int,
    y1: int,
    edge: int,
    n_cols: int,
    n_rows: int,
    w_cell: int,
    h_cell: int,
    budget: int,
    u_max: NDArray[np.int64],
) -> tuple[NDArray[np.int32], NDArray[np.float32], NDArray[np.float32], float]:
    """-> xy (K, 2) int32 level px, response (K,) float32, angle (K,) float32 degrees, weak_share."""
    xy_all, response_all = _fast9(image, min_threshold, x0, y0, x1, y1)
    n = xy_all.shape[0]
    n_cells = n_rows * n_cols
    cell = np.empty(n, np.int64)
    has_strong = np.zeros(n_cells, np.bool_)
    for i in range(n):
        col = (np.int64(xy_all[i, 0]) - edge) // w_cell
        row = (np.int64(xy_all[i, 1]) - edge) // h_cell
        cell[i] = row * n_cols + col
        if response_all[i] >= ini_threshold:
            has_strong[cell[i]] = True
    n_keep = 0
    keep = np.empty(n, np.int64)
    for i in range(n):
        if response_all[i] >= ini_threshold or not has_strong[cell[i]]:
            keep[n_keep] = i
            n_keep += 1
    n_strong_cells = 0
    for c in range(n_cells):
        n_strong_cells += has_strong[c]
    weak_share = 1.0 - n_strong_cells / n_cells
    xs = np.empty(n_keep, np.float64)
    ys = np.empty(n_keep, np.float64)
    response = np.empty(n_keep, np.float32)
    for k in range(n_keep):
        i = keep[k]
        xs[k] = xy_all[i, 0] - x0
        ys[k] = xy_all[i, 1] - y0
        response[k] = response_all[i]
    chosen = distribute_quadtree(xs, ys, response, x1 - x0, y1 - y0, budget)
    m = chosen.shape[0]
    xy = np.empty((m, 2), np.int32)
    out_response = np.empty(m, np.float32)
    for k in range(m):
        i = keep[chosen[k]]
        xy[k, 0] = xy_all[i, 0]
        xy[k, 1] = xy_all[i, 1]
        out_response[k] = response_all[i]
    angle = intensity_centroid_angles(image, xy, u_max)
    return xy, out_response, angle, weak_share


@njit(cache=True, nogil=True)
def _levels_keypoints(  # pragma: no cover - compiled
    images: tuple[NDArray[np.uint8], ...],
    params: NDArray[np.int64],
    u_max: NDArray[np.int64],
) -> tuple[NDArray[np.int32], NDArray[np.float32], NDArray[np.float32], NDArray[np.int64], NDArray[np.float64]]:
    """_level_keypoints on several levels in one call. params (L, 13): per level min/ini threshold, region x0 y0
    x1 y1, grid edge n_cols n_rows w_cell h_cell, budget, and 1 if the level is large enough for FAST. Returns
    the levels' xy, response, angle concatenated in order, counts (L,) and weak shares (L,)."""
    n_levels = params.shape[0]
    counts = np.zeros(n_levels, np.int64)
    weak = np.ones(n_levels, np.float64)
    parts_xy = []
    parts_response = []
    parts_angle = []
    for k in range(n_levels):
        p = params[k]
        if p[12] == 0:
            continue
        xy, response, angle, weak_share = _level_keypoints(
            images[k], p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7], p[8], p[9], p[10], p[11], u_max
        )
        counts[k] = xy.shape[0]
        weak[k] = weak_share
        parts_xy.append(xy)
        parts_response.append(response)
        parts_angle.append(angle)
    total = counts.sum()
    xy_all = np.empty((total, 2), np.int32)
    response_all = np.empty(total, np.float32)
    angle_all = np.empty(total, np.float32)
    at = 0
    for j in range(len(parts_xy)):
        m = parts_xy[j].shape[0]
        xy_all[at : at + m] = parts_xy[j]
        response_all[at : at + m] = parts_response[j]
        angle_all[at : at + m] = parts_angle[j]
        at += m
    return xy_all, response_all, angle_all, counts, weak


def _level_params(grid: GridFast, image: NDArray[np.uint8], budget: int) -> NDArray[np.int64]:
    """(13,) int64 kernel parameters of one level (see _levels_keypoints); the last is 0 when the level is too
    small for FAST (its detection area 2 * FAST_RADIUS px or less on a side)."""
    params = np.zeros(13, np.int64)
    h, w = image.shape
    x0, y0, x1, y1 = grid.region(w, h)
    if x1 - x0 > 2 * FAST_RADIUS and y1 - y0 > 2 * FAST_RADIUS:
        c = grid.cells(x0, y0, x1, y1)
        params[:6] = (grid.min_threshold, grid.ini_threshold, x0, y0, x1, y1)
        params[6:] = (c.edge, c.n_cols, c.n_rows, c.w_cell, c.h_cell, int(budget), 1)
    return params


def levels_keypoints(
    grid: GridFast, level_images: list[NDArray[np.uint8]], budgets: list[int], u_max: NDArray[np.int64]
) -> tuple[NDArray[np.int32], NDArray[np.float32], NDArray[np.float32], NDArray[np.int64], NDArray[np.float64]]:
    """``level_keypoints`` of several levels in one GIL-free call (one GIL hand-over instead of one per level).

    Returns xy (K, 2) int32, response (K,), angle (K,) of all the levels in the given order, counts (L,) per
    level and weak shares (L,).
    """
    images = tuple(np.ascontiguousarray(img) for img in level_images)
    params = np.array([_level_params(grid, img, b) for img, b in zip(images, budgets, strict=True)], np.int64)
    return _levels_keypoints(images, params.reshape(len(images), 13), u_max)


def level_keypoints(
    grid: GridFast, level_image: NDArray[np.uint8], budget: int, u_max: NDArray[np.int64]
) -> tuple[NDArray[np.int32], NDArray[np.float32], NDArray[np.float32], float]:
    """The keypoints ORB-SLAM keeps on one level, oriented.

    grid: the level's FAST grid (thresholds, cells, border); level_image: (h, w) uint8; budget: the level's
    share of the features; u_max: the orientation patch (orientation.circular_patch_extent). Returns xy (K, 2)
    int32 level px in ascending corner order, response (K,) float32 FAST scores, angle (K,) float32 degrees in
    [0, 360), and the share of grid cells without a corner at the initial threshold (1.0 when the level is too
    small for FAST). Equals GridFast.detect(..., "whole") -> distribute_quadtree -> intensity_centroid_angles.
    """
    xy, response, angle, _, weak = levels_keypoints(grid, [level_image], [budget], u_max)
    return xy, response, angle, float(weak[0])
