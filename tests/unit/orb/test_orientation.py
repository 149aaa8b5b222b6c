"""Orientation by intensity centroid: the circular patch and angles of known synthetic patterns."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from slamkit_orb.orbslam_extractor import OrbSlamExtractor
from slamkit_orb.orientation import circular_patch_extent, intensity_centroid_angles


def test_patch_extent_is_orbs_circle_of_radius_15() -> None:
    u_max = circular_patch_extent(15)
    assert u_max.tolist() == [15, 15, 15, 15, 14, 14, 14, 13, 13, 12, 11, 10, 9, 8, 6, 3]
    # Symmetric under a 90 deg turn: (u, v) in the patch <=> (v, u) in the patch.
    inside = {(u, v) for v in range(-15, 16) for u in range(-int(u_max[abs(v)]), int(u_max[abs(v)]) + 1)}
    assert inside == {(v, u) for u, v in inside}


@pytest.mark.parametrize(("dx", "dy"), [(5, 0), (0, 7), (-9, 0), (0, -3), (4, 4), (-6, 2), (10, -5)])
def test_angle_points_to_a_single_bright_pixel(dx: int, dy: int) -> None:
    image = np.zeros((60, 60), np.uint8)
    image[30 + dy, 30 + dx] = 255
    angle = intensity_centroid_angles(image, np.array([[30, 30]], np.int32), circular_patch_extent(15))
    expected = math.degrees(math.atan2(dy, dx)) % 360.0
    assert angle[0] == pytest.approx(expected, abs=1e-4)


def test_pixels_outside_the_circle_are_ignored() -> None:
    image = np.zeros((60, 60), np.uint8)
    image[30 + 14, 30 + 14] = 255  # inside the 31x31 square, outside the radius-15 circle
    image[30, 30 - 2] = 255
    angle = intensity_centroid_angles(image, np.array([[30, 30]], np.int32), circular_patch_extent(15))
    assert angle[0] == pytest.approx(180.0)


@pytest.mark.parametrize("direction_deg", [0.0, 37.0, 100.0, 215.0, 290.0])
def test_extractor_orients_a_wedge_along_its_bisector(direction_deg: float) -> None:
    """A bright 50 deg wedge with its apex at the image centre: the apex keypoint points into the wedge."""
    image = np.full((240, 320), 40, np.uint8)
    apex = np.array([160.0, 120.0])
    pts = [apex]
    for side in (-25.0, 25.0):
        a = math.radians(direction_deg + side)
        pts.append(apex + 80.0 * np.array([math.cos(a), math.sin(a)]))  # image y points down, like v
    cv2.fillPoly(image, [np.rint(np.array(pts) * 16).astype(np.int32)], 220, cv2.LINE_AA, shift=4)
    features = OrbSlamExtractor(n_features=200, n_threads=1).extract(image)
    # FAST fires a pixel or two inside a sharp apex, on several pyramid levels.
    near = np.linalg.norm(features.uv_px - apex, axis=1) < 5.0
    assert np.count_nonzero(near) >= 1
    error = (features.angle_deg[near] - direction_deg + 180.0) % 360.0 - 180.0
    assert np.all(np.abs(error) < 6.0)
