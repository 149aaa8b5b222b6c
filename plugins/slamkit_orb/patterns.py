"""Seeded synthetic grey images for testing and benchmarking feature extractors (no files needed).

Images are random filled shapes (rectangles, discs, triangles, thick lines) drawn with OpenCV; the grey
levels of the shapes bound the local contrast, hence which FAST threshold finds their corners.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

U8 = NDArray[np.uint8]


def draw_shapes(
    canvas: U8,
    rng: np.random.Generator,
    n_shapes: int,
    grey_range: tuple[int, int],
    box: tuple[int, int, int, int] | None = None,
    size_range_px: tuple[float, float] = (6.0, 40.0),
) -> U8:
    """Draw ``n_shapes`` random shapes with grey levels in ``grey_range`` (inclusive) into ``canvas``.

    canvas: (H, W) uint8, modified in place and returned. box: (x0, y0, x1, y1) px the shapes are clipped
    to (whole image if None). size_range_px: shape size, px.
    """
    x0, y0, x1, y1 = box if box is not None else (0, 0, canvas.shape[1], canvas.shape[0])
    region = canvas[y0:y1, x0:x1].copy()
    h, w = region.shape
    lo, hi = grey_range
    for _ in range(n_shapes):
        kind = int(rng.integers(4))
        grey = int(rng.integers(lo, hi + 1))
        cx, cy = float(rng.uniform(0, w)), float(rng.uniform(0, h))
        size = float(rng.uniform(*size_range_px))
        if kind == 0:
            angle = float(rng.uniform(0, 180))
            corners = cv2.boxPoints(((cx, cy), (size, size * float(rng.uniform(0.3, 1.0))), angle))
            cv2.fillPoly(region, [np.rint(corners).astype(np.int32)], grey, cv2.LINE_8)
        elif kind == 1:
            cv2.circle(region, (round(cx), round(cy)), max(2, round(size / 2)), grey, -1, cv2.LINE_8)
        elif kind == 2:
            pts = np.array([cx, cy]) + rng.uniform(-size, size, size=(3, 2))
            cv2.fillPoly(region, [np.rint(pts).astype(np.int32)], grey, cv2.LINE_8)
        else:
            p2 = np.array([cx, cy]) + rng.uniform(-2 * size, 2 * size, size=2)
            thickness = int(rng.integers(2, 6))
            cv2.line(region, (round(cx), round(cy)), (round(p2[0]), round(p2[1])), grey, thickness, cv2.LINE_8)
    canvas[y0:y1, x0:x1] = region
    return canvas


def textured_image(seed: int, width: int = 640, height: int = 480) -> U8:
    """(height, width) uint8: high-contrast shapes all over a mid-grey background."""
    rng = np.random.default_rng(seed)
    img = np.full((height, width), 128, dtype=np.uint8)
    n = max(1, width * height // 600)
    return draw_shapes(img, rng, n, (0, 255))


def uneven_texture_image(
    seed: int,
    width: int = 640,
    height: int = 480,
    weak_grey_range: tuple[int, int] = (128, 142),
    strong_fraction: float = 0.3,
) -> U8:
    """(height, width) uint8: one densely textured high-contrast block at the top left (``strong_fraction`` of
    the width and of the height), weak texture elsewhere.

    The weak shapes have grey levels in ``weak_grey_range`` on a background of its lower end, so no two
    neighbouring pixels there differ by more than its span: with the default (128, 142), a span of 14, FAST
    at threshold 20 finds nothing in the weak part and FAST at 7 does.
    """
    rng = np.random.default_rng(seed)
    img = np.full((height, width), weak_grey_range[0], dtype=np.uint8)
    draw_shapes(img, rng, max(1, width * height // 1500), weak_grey_range)
    sw, sh = round(width * strong_fraction), round(height * strong_fraction)
    strong_n = max(1, sw * sh // 80)
    draw_shapes(img, rng, strong_n, (0, 255), box=(0, 0, sw, sh), size_range_px=(3.0, 12.0))
    return img
