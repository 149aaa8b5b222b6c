"""rBRIEF descriptors: computed as ORB-SLAM does (level image, keypoint angle) and invariant to rotation."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray
from slamkit_orb.orbslam_extractor import OrbSlamExtractor
from slamkit_orb.patterns import textured_image

from slamkit.features import Features


def _hamming(a: NDArray[np.uint8], b: NDArray[np.uint8]) -> NDArray[np.int64]:
    return np.unpackbits(a ^ b, axis=1).sum(axis=1).astype(np.int64)


def test_per_level_descriptors_equal_opencvs_multi_level_computation(extractor: OrbSlamExtractor) -> None:
    """The extractor computes each level's descriptors on its level image at octave 0; OpenCV computing on the
    full image with octave = level (its own pyramid, blur, pattern and scaling) must give the same bits."""
    image = textured_image(seed=21)
    features = extractor.extract(image)
    assert set(features.level.tolist()) == set(range(8))
    keypoints = [
        cv2.KeyPoint(float(u), float(v), 31.0, float(a), 1.0, int(o), i)
        for i, ((u, v), a, o) in enumerate(zip(features.uv_px, features.angle_deg, features.level, strict=True))
    ]
    orb = cv2.ORB.create(nfeatures=1000, scaleFactor=1.2, nlevels=8, edgeThreshold=19, patchSize=31)
    kept, descriptors = orb.compute(image, keypoints)
    assert [k.class_id for k in kept] == list(range(len(features)))
    np.testing.assert_array_equal(descriptors, features.descriptors)


def _rotated_pairs(features: Features, rotated: Features, width: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Index pairs of keypoints at the same level whose positions correspond under np.rot90 (x, y) -> (y, W-1-x)."""
    where = {
        (round(float(u)), round(float(v)), int(o)): j
        for j, ((u, v), o) in enumerate(zip(rotated.uv_px, rotated.level, strict=True))
    }
    pairs = []
    for i, ((u, v), o) in enumerate(zip(features.uv_px, features.level, strict=True)):
        j = where.get((round(float(v)), round(width - 1 - float(u)), int(o)))
        if j is not None and o == 0:
            pairs.append((i, j))
    idx = np.array(pairs, dtype=np.int64).reshape(-1, 2)
    return idx[:, 0], idx[:, 1]


@pytest.mark.parametrize("seed", [11, 12])
def test_descriptors_and_angles_are_invariant_to_a_90_degree_turn(extractor: OrbSlamExtractor, seed: int) -> None:
    image = textured_image(seed=seed)
    rotated_image = np.ascontiguousarray(np.rot90(image))  # counter-clockwise: (x, y) -> (y, W - 1 - x)
    features, rotated = extractor.extract(image), extractor.extract(rotated_image)
    i, j = _rotated_pairs(features, rotated, image.shape[1])
    assert i.size > 100
    # A counter-clockwise turn of the image (y down) subtracts 90 deg from every direction.
    turn = (features.angle_deg[i] - 90.0 - rotated.angle_deg[j] + 180.0) % 360.0 - 180.0
    assert np.abs(turn).max() < 1e-3
    distance = _hamming(features.descriptors[i], rotated.descriptors[j])
    assert np.median(distance) == 0 and np.percentile(distance, 95) <= 2

    # Control: the same keypoints described without steering (angle 0) are far apart after the turn.
    orb = cv2.ORB.create(edgeThreshold=19, patchSize=31)
    plain = [cv2.KeyPoint(float(u), float(v), 31.0, 0.0) for u, v in features.uv_px[i]]
    plain_rot = [cv2.KeyPoint(float(u), float(v), 31.0, 0.0) for u, v in rotated.uv_px[j]]
    d0 = np.asarray(orb.compute(image, plain)[1], np.uint8)
    d1 = np.asarray(orb.compute(rotated_image, plain_rot)[1], np.uint8)
    assert np.median(_hamming(d0, d1).astype(np.float64)) > 60


def test_descriptors_of_a_real_image_survive_the_turn(
    extractor: OrbSlamExtractor, tum_image: NDArray[np.uint8]
) -> None:
    rotated_image = np.ascontiguousarray(np.rot90(tum_image))
    features, rotated = extractor.extract(tum_image), extractor.extract(rotated_image)
    i, j = _rotated_pairs(features, rotated, tum_image.shape[1])
    assert i.size > 100
    assert np.percentile(_hamming(features.descriptors[i], rotated.descriptors[j]), 95) <= 2


def test_keypoints_opencv_drops_leave_the_others_with_their_own_descriptors(extractor: OrbSlamExtractor) -> None:
    """A keypoint inside OpenCV's border is dropped by ``compute``: the level result keeps the others, in their
    input order, each with the descriptor OpenCV gives it alone (the rows are found by position, not class_id)."""
    image = textured_image(seed=5)
    h, w = image.shape
    rng = np.random.default_rng(3)
    inner = np.stack([rng.choice(np.arange(40, w - 40), 60, replace=False), rng.integers(40, h - 40, 60)], axis=1)
    edge = np.array([[2, 100], [w - 3, 50], [200, 1]])  # within edge_threshold of the border: dropped
    xy = np.concatenate([inner[:20], edge[:1], inner[20:45], edge[1:], inner[45:]]).astype(np.int32)
    response = np.arange(xy.shape[0], dtype=np.float32)
    angle = np.asarray(rng.uniform(0.0, 360.0, xy.shape[0]), np.float32)
    out = extractor._described(0, image, xy, response, angle)
    is_inner = np.ones(xy.shape[0], bool)
    is_inner[[20, 46, 47]] = False
    np.testing.assert_array_equal(out.xy, xy[is_inner])
    np.testing.assert_array_equal(out.response, response[is_inner])
    for k in range(0, out.xy.shape[0], 9):
        alone = extractor._described(0, image, out.xy[k : k + 1], out.response[k : k + 1], out.angle_deg[k : k + 1])
        np.testing.assert_array_equal(alone.descriptors[0], out.descriptors[k])
