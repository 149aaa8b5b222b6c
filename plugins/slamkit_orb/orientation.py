"""Keypoint orientation by intensity centroid (ORB, Rublee et al. 2011; ORB-SLAM's ``IC_Angle``).

The angle is that of the vector from the keypoint to the intensity centroid of a circular patch around it:
atan2(m01, m10) with m10 = sum u I(x + u, y + v), m01 = sum v I(x + u, y + v) over the patch (v grows
downwards, so the angle turns clockwise on screen, as in OpenCV). ORB-SLAM takes it with OpenCV's
``fastAtan2`` (about 0.3 deg error); here it is exact.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray


def circular_patch_extent(half_patch_size: int) -> NDArray[np.int64]:
    """(half_patch_size + 1,) u_max: the patch row v spans u in [-u_max[|v|], u_max[|v|]].

    Rows up to 45 deg take round(sqrt(r^2 - v^2)); the rest are mirrored from the columns so the patch is
    symmetric under a 90 deg rotation (ORB's construction), which keeps the angle exact under such turns.
    """
    r = int(half_patch_size)
    u_max = np.zeros(r + 1, dtype=np.int64)
    v_max = math.floor(r * math.sqrt(2.0) / 2.0 + 1.0)
    v_min = math.ceil(r * math.sqrt(2.0) / 2.0)
    for v in range(min(v_max, r) + 1):
        u_max[v] = round(math.sqrt(r * r - v * v))
    # Mirror: row v (beyond 45 deg) extends as far as the lowest column whose extent reaches v.
    v0 = 0
    for v in range(r, v_min - 1, -1):
        while u_max[v0] == u_max[v0 + 1]:
            v0 += 1
        u_max[v] = v0
        v0 += 1
    return u_max


@njit(cache=True, nogil=True)
def intensity_centroid_angles(
    image: NDArray[np.uint8], xy: NDArray[np.int32], u_max: NDArray[np.int64]
) -> NDArray[np.float32]:
    """image: (h, w) uint8 level image; xy: (N, 2) int32 keypoint column/row on it, at least
    len(u_max) - 1 px from every border -> (N,) float32 angles in degrees, [0, 360)."""
    r = u_max.shape[0] - 1
    out = np.empty(xy.shape[0], dtype=np.float32)
    for k in range(xy.shape[0]):
        cx, cy = xy[k, 0], xy[k, 1]
        m10 = np.int64(0)
        m01 = np.int64(0)
        for u in range(-r, r + 1):
            m10 += u * np.int64(image[cy, cx + u])
        for v in range(1, r + 1):
            d = u_max[v]
            for u in range(-d, d + 1):
                below = np.int64(image[cy + v, cx + u])
                above = np.int64(image[cy - v, cx + u])
                m10 += u * (below + above)
                m01 += v * (below - above)
        angle = math.degrees(math.atan2(float(m01), float(m10)))
        if angle < 0.0:
            angle += 360.0
        a32 = np.float32(angle)
        out[k] = a32 if a32 < np.float32(360.0) else np.float32(0.0)
    return out
