"""ORB-SLAM's scale pyramid: level scales and sizes, the per-level feature budget, and the level images.

Level ``l`` is the image shrunk by ``scale_factor ** l``. Sizes and scales are computed in float32 exactly as
OpenCV's ORB does, and each level is resized from the one above it with ``INTER_LINEAR_EXACT``, so the level
images here are pixel-for-pixel those OpenCV builds when it computes descriptors for our keypoints
(``cv2.ORB.compute``): detection, orientation and descriptor all see the same level image. (ORB-SLAM itself
resizes with ``INTER_LINEAR``; the two differ by up to 3 grey levels, on about a fifth of all the pyramid's pixels
of room and KITTI frames: docs/BENCHMARKS.md, issue 16 branch ``stspeed``.)
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray


def level_scales(scale_factor: float, n_levels: int) -> NDArray[np.float32]:
    """(n_levels,) float32 scale of each level w.r.t. level 0: scale_factor ** level (OpenCV's ``getScale``)."""
    return np.array([np.float32(scale_factor**level) for level in range(n_levels)], dtype=np.float32)


def level_sizes(width: int, height: int, scale_factor: float, n_levels: int) -> list[tuple[int, int]]:
    """(width, height) px of each level: round(size / scale) in float32, ties to even (OpenCV's cvRound)."""
    sizes = []
    for scale in level_scales(scale_factor, n_levels):
        inv = np.float32(1.0) / scale
        sizes.append((int(np.rint(np.float32(width) * inv)), int(np.rint(np.float32(height) * inv))))
    return sizes


def features_per_level(n_features: int, scale_factor: float, n_levels: int) -> NDArray[np.int64]:
    """(n_levels,) ORB-SLAM's split of the feature budget over the levels.

    Each level gets 1/scale_factor of the share of the level below (a geometric series whose n_levels
    terms sum to n_features), rounded; the last level takes what is left so the total is exactly
    n_features.
    """
    factor = 1.0 / scale_factor
    share = n_features * (1.0 - factor) / (1.0 - factor**n_levels)
    budget = np.zeros(n_levels, dtype=np.int64)
    for level in range(n_levels - 1):
        budget[level] = round(share)
        share *= factor
    budget[n_levels - 1] = max(n_features - int(budget[: n_levels - 1].sum()), 0)
    return budget


def build_pyramid(image: NDArray[np.uint8], sizes: list[tuple[int, int]]) -> list[NDArray[np.uint8]]:
    """image: (H, W) uint8 level 0 -> one (h, w) uint8 image per entry of ``sizes`` (each resized from the
    previous level); stops early at a size with a zero side."""
    levels = [image]
    for w, h in sizes[1:]:
        if w < 1 or h < 1:
            break
        levels.append(np.asarray(cv2.resize(levels[-1], (w, h), interpolation=cv2.INTER_LINEAR_EXACT), np.uint8))
    return levels


@dataclass(frozen=True)
class PackedPyramid:
    """The level images of :func:`build_pyramid` stored row-major one after the other in one uint8 array (the
    layout a compiled kernel reads a whole pyramid from, e.g. stereo matching's SAD windows).

    pixels: (sum of w x h,) uint8; offsets, widths, heights: (n_levels,) int64, level l is
    ``pixels[offsets[l] : offsets[l] + widths[l] * heights[l]]`` reshaped (heights[l], widths[l]); a level past an
    empty one has width and height 0. levels: the non-empty levels as (h, w) views of ``pixels`` (what
    :func:`build_pyramid` returns, with level 0 a copy of the image).
    """

    pixels: NDArray[np.uint8]
    offsets: NDArray[np.int64]
    widths: NDArray[np.int64]
    heights: NDArray[np.int64]
    levels: list[NDArray[np.uint8]]

    def packed(self) -> tuple[NDArray[np.uint8], NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
        """(pixels, offsets, widths, heights)."""
        return self.pixels, self.offsets, self.widths, self.heights


def build_packed_pyramid(image: NDArray[np.uint8], sizes: list[tuple[int, int]]) -> PackedPyramid:
    """:func:`build_pyramid` with every level resized straight into its place in one packed array (the same pixels:
    the same INTER_LINEAR_EXACT resizes of the same sources); one entry per size, zero-sized from the first
    empty level on."""
    n = len(sizes)
    widths = np.zeros(n, np.int64)
    heights = np.zeros(n, np.int64)
    for k, (w, h) in enumerate(sizes):
        if k and (w < 1 or h < 1):
            break
        widths[k], heights[k] = w, h
    h0, w0 = image.shape[:2]
    widths[0], heights[0] = w0, h0
    area = widths * heights
    offsets = np.zeros(n, np.int64)
    offsets[1:] = np.cumsum(area)[:-1]
    pixels = np.empty(int(area.sum()), np.uint8)
    levels = [pixels[: w0 * h0].reshape(h0, w0)]
    levels[0][...] = image
    for k in range(1, n):
        w, h = int(widths[k]), int(heights[k])
        if w == 0:
            break
        level = pixels[int(offsets[k]) : int(offsets[k]) + w * h].reshape(h, w)
        out = cv2.resize(levels[-1], (w, h), dst=level, interpolation=cv2.INTER_LINEAR_EXACT)
        if not np.shares_memory(out, level):  # OpenCV allocated its own output after all
            level[...] = out
        levels.append(level)
    return PackedPyramid(pixels, offsets, widths, heights, levels)
