"""FAST-9/16 corners with non-maximum suppression, compiled with numba, equal to OpenCV's bit for bit.

``fast9_corners`` returns exactly what ``cv2.FastFeatureDetector.create(threshold, nonmaxSuppression=True,
type=TYPE_9_16).detect`` returns (OpenCV's ``FAST_t<16>`` in fast.cpp and ``cornerScore<16>`` in
fast_score.cpp), as numpy arrays instead of one ``cv2.KeyPoint`` per corner, and without holding the GIL.

Definitions (OpenCV's, which this module reproduces):
- The circle: the 16 pixels p_0..p_15 of the Bresenham circle of radius 3 around the centre value v, in
  circular order. A pixel is a corner at threshold t when 9 circularly contiguous p_k are all > v + t
  (brighter) or all < v - t (darker). Only pixels at least 3 px from every image border are tested.
- The score: the largest t at which the pixel is still a corner, i.e. max over the 16 arcs of 9 contiguous
  circle pixels of min over the arc of |v - p_k| (for an arc all on one side of v), minus 1. It does not
  depend on the threshold the detector runs with (a corner at t has score >= t).
- Non-maximum suppression: a corner survives when its score is strictly greater than the stored value of
  each of its 8 neighbours, the stored value being the neighbour's score if it is a corner at t, else 0
  (also beyond the 3 px border). So a corner of score 0 (possible at t = 0 only) never survives, and of two
  adjacent corners of equal score neither does.
- Output order is raster order (row, then column); positions are integers (OpenCV's float ``pt`` is
  exactly the integer pixel), ``response`` is the score as float.

How it is computed (the formulation matters for speed): the score is computed for every pixel in a
branch-free loop over the row that LLVM vectorises (32 or 64 pixels per instruction, uint8 lanes).
min over an arc of (v - p_k) is v - max over the arc of p_k, so the darker score is v - P with P = min over
arcs of the arc maximum, the brighter one Q - v with Q = max over arcs of the arc minimum (both saturated
at 0, so no arc on that side gives 0); m = max(v - P, Q - v) > t exactly when the pixel is a corner at t,
and then its score is m - 1. The 16 arc extremes share work as in a sliding-window maximum: pairs, then
quadruples, then the 8 windows of 8 starting at odd k, each extended by p_k or p_(k+9) to the two arcs of
9 that contain it (47 min/max operations per side). Rows stream through a ring of three score rows: once
row r + 1 is scored, a second vectorised loop applies the suppression to row r and a scan of 8 flags at a
time (one 64-bit word) collects its survivors. Array indices are unsigned so numba emits no
negative-index wrap-around, which would stop the vectoriser.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

#: The circle's radius: no corner within this many px of the image (or rectangle) border.
FAST_RADIUS = 3
_MIN_SIDE = 2 * FAST_RADIUS + 1

# Unsigned index constants: with unsigned indices numba does not wrap negative indices around (see above).
U0 = np.uint64(0)
U1 = np.uint64(1)
U2 = np.uint64(2)
U3 = np.uint64(3)
U4 = np.uint64(4)
U5 = np.uint64(5)
U6 = np.uint64(6)
_BYTE_ONES = np.uint64(0x0101010101010101)
_TOP_BYTE_SHIFT = np.uint64(56)


@njit(cache=True, nogil=True)
def _score_row(
    image: NDArray[np.uint8], t: np.uint8, y: np.uint64, xb: np.uint64, n: int, out: NDArray[np.uint8]
) -> None:
    """Stored scores of image row y, columns xb + 3 .. xb + 2 + n, into out[3 : 3 + n]: the score of a corner
    at threshold t, else 0 (OpenCV's suppression buffer). Rows y - 3 .. y + 3 and columns xb .. xb + n + 5
    lie inside the image."""
    for i in range(np.uint64(n)):
        x = xb + i  # column of the circle's leftmost pixels; the centre is x + 3
        # Circle pixels p0..p15 clockwise from straight below (offsets as in OpenCV's makeOffsets).
        p0 = image[y + U3, x + U3]
        p1 = image[y + U3, x + U4]
        p2 = image[y + U2, x + U5]
        p3 = image[y + U1, x + U6]
        p4 = image[y, x + U6]
        p5 = image[y - U1, x + U6]
        p6 = image[y - U2, x + U5]
        p7 = image[y - U3, x + U4]
        p8 = image[y - U3, x + U3]
        p9 = image[y - U3, x + U2]
        p10 = image[y - U2, x + U1]
        p11 = image[y - U1, x]
        p12 = image[y, x]
        p13 = image[y + U1, x]
        p14 = image[y + U2, x + U1]
        p15 = image[y + U3, x + U2]
        v = image[y, x + U3]

        # Darker side: P = min over the 16 arcs of 9 of the arc's maximum.
        # a_k: max of p_k, p_k+1 (k odd); b_k: of p_k..p_k+3; c_k: of p_k..p_k+7.
        a1, a3, a5, a7 = max(p1, p2), max(p3, p4), max(p5, p6), max(p7, p8)
        a9, a11, a13, a15 = max(p9, p10), max(p11, p12), max(p13, p14), max(p15, p0)
        b1, b3, b5, b7 = max(a1, a3), max(a3, a5), max(a5, a7), max(a7, a9)
        b9, b11, b13, b15 = max(a9, a11), max(a11, a13), max(a13, a15), max(a15, a1)
        c1, c3, c5, c7 = max(b1, b5), max(b3, b7), max(b5, b9), max(b7, b11)
        c9, c11, c13, c15 = max(b9, b13), max(b11, b15), max(b13, b1), max(b15, b3)
        # Arcs k..k+8 and k+1..k+9 (k even) share c_(k+1): min(max(c, p_k), max(c, p_k+9)).
        dark = min(
            min(
                min(max(c1, min(p0, p9)), max(c3, min(p2, p11))),
                min(max(c5, min(p4, p13)), max(c7, min(p6, p15))),
            ),
            min(
                min(max(c9, min(p8, p1)), max(c11, min(p10, p3))),
                min(max(c13, min(p12, p5)), max(c15, min(p14, p7))),
            ),
        )
        # Brighter side: Q = max over the arcs of the arc's minimum (same scheme, min and max swapped).
        a1, a3, a5, a7 = min(p1, p2), min(p3, p4), min(p5, p6), min(p7, p8)
        a9, a11, a13, a15 = min(p9, p10), min(p11, p12), min(p13, p14), min(p15, p0)
        b1, b3, b5, b7 = min(a1, a3), min(a3, a5), min(a5, a7), min(a7, a9)
        b9, b11, b13, b15 = min(a9, a11), min(a11, a13), min(a13, a15), min(a15, a1)
        c1, c3, c5, c7 = min(b1, b5), min(b3, b7), min(b5, b9), min(b7, b11)
        c9, c11, c13, c15 = min(b9, b13), min(b11, b15), min(b13, b1), min(b15, b3)
        bright = max(
            max(
                max(min(c1, max(p0, p9)), min(c3, max(p2, p11))),
                max(min(c5, max(p4, p13)), min(c7, max(p6, p15))),
            ),
            max(
                max(min(c9, max(p8, p1)), min(c11, max(p10, p3))),
                max(min(c13, max(p12, p5)), min(c15, max(p14, p7))),
            ),
        )
        # uint8 casts keep the arithmetic in byte lanes (numba would widen it to int64).
        m = max(np.uint8(v - min(dark, v)), np.uint8(max(bright, v) - v))
        out[i + U3] = np.uint8(m - np.uint8(1)) if m > t else np.uint8(0)


@njit(cache=True, nogil=True)
def _suppress_row(
    above: NDArray[np.uint8], here: NDArray[np.uint8], below: NDArray[np.uint8], n: int, flags: NDArray[np.uint8]
) -> None:
    """flags[i] = 1 where the stored score here[i + 3] beats all 8 neighbours', for i < n."""
    for i in range(np.uint64(n)):
        x = i + U2  # left neighbour of the pixel at column i + 3
        neighbours = max(
            max(max(above[x], above[x + U1]), max(above[x + U2], here[x])),
            max(max(here[x + U2], below[x]), max(below[x + U1], below[x + U2])),
        )
        flags[i] = here[x + U1] > neighbours


@njit(cache=True, nogil=True)
def _fast9(
    image: NDArray[np.uint8], threshold: int, x0: int, y0: int, x1: int, y1: int
) -> tuple[NDArray[np.int32], NDArray[np.float32]]:
    """FAST of image[y0:y1, x0:x1] (sides >= 7 px, inside the image) -> (N, 2) int32 image px, (N,) float32
    scores, in raster order. Rows stream through a ring of three stored-score rows: row r is suppressed
    once row r + 1 is scored."""
    height, width = y1 - y0, x1 - x0
    n_cols = width - 2 * FAST_RADIUS
    n_rows = height - 2 * FAST_RADIUS
    # No two survivors are 8-neighbours, so at most every other pixel in both directions survives.
    capacity = ((n_cols + 1) // 2) * ((n_rows + 1) // 2)
    xy = np.empty((capacity, 2), np.int32)
    score = np.empty(capacity, np.float32)
    # Stored-score rows r % 3 of the crop; columns < 3 and >= width - 3 stay 0 (beyond the border).
    ring = np.zeros((3, width), np.uint8)
    n_words = (n_cols + 7) // 8
    flags = np.zeros(n_words * 8, np.uint8)  # the tail past n_cols stays 0
    words = flags.view(np.uint64)
    t = np.uint8(threshold)
    xb = np.uint64(x0)
    count = 0
    # Rows 3 .. height - 4 are scored; row 2 (ring slot 2) and row height - 3 count as all 0.
    for r in range(FAST_RADIUS, height - FAST_RADIUS + 1):
        if r < height - FAST_RADIUS:
            _score_row(image, t, np.uint64(y0 + r), xb, n_cols, ring[r % 3])
        else:
            ring[r % 3, :] = 0
        row = r - 1
        if row < FAST_RADIUS:
            continue
        here = ring[row % 3]
        _suppress_row(ring[(row - 1) % 3], here, ring[r % 3], n_cols, flags)
        for k in range(n_words):
            word = words[k]
            while word != U0:
                # Lowest set flag byte: its lowest bit b = 2^(8j); (b - 1) has j bytes 0xFF, whose low bits
                # summed by the multiply land in the top byte: j.
                low = word & (~word + U1)
                j = ((((low - U1) & _BYTE_ONES) * _BYTE_ONES) >> _TOP_BYTE_SHIFT) + np.uint64(8 * k)
                word ^= low
                col = j + U3
                xy[count, 0] = x0 + np.int64(col)
                xy[count, 1] = y0 + row
                score[count] = here[col]
                count += 1
    return xy[:count].copy(), score[:count].copy()


def _check_threshold(threshold: object) -> int:
    if isinstance(threshold, bool) or not isinstance(threshold, int | np.integer) or not 0 <= threshold <= 255:
        # OpenCV clamps to [0, 255] in its scalar code but not in its SIMD code, so outside that range its
        # result is not even self-consistent: refuse rather than guess.
        raise ValueError(f"fast9_corners: threshold must be an integer in [0, 255] grey levels, got {threshold!r}")
    return int(threshold)


def fast9_corners(
    image: NDArray[np.uint8], threshold: int, rect: tuple[int, int, int, int] | None = None
) -> tuple[NDArray[np.int32], NDArray[np.float32]]:
    """FAST-9/16 corners with non-maximum suppression, exactly as OpenCV's FastFeatureDetector finds them.

    image: (H, W) uint8 grey. Any strides are accepted; a non-C-contiguous view is copied first.
    threshold: grey levels in [0, 255]; a circle pixel must differ from the centre by more than this.
    rect: optional (x0, y0, x1, y1) px, 0 <= x0 <= x1 <= W, 0 <= y0 <= y1 <= H: detect as OpenCV does on the
        crop image[y0:y1, x0:x1] (nothing within 3 px of the crop's border, suppression only among the
        crop's corners), without copying it.

    Returns xy: (N, 2) int32 column/row in ``image`` px (crop coordinates plus (x0, y0)), in raster order;
    score: (N,) float32 FAST score (grey levels, >= threshold). Equal to OpenCV means: the same N, and
    xy[i] == KeyPoint.pt (always whole pixels) and score[i] == KeyPoint.response of the i-th keypoint of
    ``detect(image[y0:y1, x0:x1])`` shifted by (x0, y0). Runs without the GIL.
    """
    if not isinstance(image, np.ndarray) or image.ndim != 2 or image.dtype != np.uint8:
        got = f"{image.shape} {image.dtype}" if isinstance(image, np.ndarray) else type(image).__name__
        raise ValueError(f"fast9_corners: image must be an (H, W) uint8 grey array, got {got}")
    t = _check_threshold(threshold)
    h, w = image.shape
    if rect is None:
        x0, y0, x1, y1 = 0, 0, w, h
    else:
        x0, y0, x1, y1 = (int(c) for c in rect)
        if not (0 <= x0 <= x1 <= w and 0 <= y0 <= y1 <= h):
            raise ValueError(
                f"fast9_corners: rect must satisfy 0 <= x0 <= x1 <= {w} and 0 <= y0 <= y1 <= {h} for a "
                f"{w}x{h} image, got {rect!r}"
            )
    if x1 - x0 < _MIN_SIDE or y1 - y0 < _MIN_SIDE:
        return np.zeros((0, 2), np.int32), np.zeros(0, np.float32)
    image = np.ascontiguousarray(image)
    return _fast9(image, t, x0, y0, x1, y1)
