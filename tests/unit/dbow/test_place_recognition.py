"""The shipped vocabulary at work: L1 score properties, place recognition on the synthetic long_loop, and
BoW-guided matching between two views checked against ground truth."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray
from slamkit_dbow.matching import match_by_bow, node_pairs
from slamkit_dbow.recognizer import DbowPlaceRecognizer
from slamkit_dbow.vocabulary import Vocabulary, VocabularyError

from slamkit.features import Features
from slamkit.interfaces import BowDescription, FeatureExtractor, PlaceRecognizer
from slamkit.io.synthetic.dataset import SyntheticDataset
from slamkit.pipeline.config import MatcherConfig

#: ORB-SLAM's SearchByBoW thresholds, as the pipeline passes them (pipeline.matcher).
ORB_MATCHER = {"max_distance": MatcherConfig().th_low, "rotation_bins": MatcherConfig().rotation_bins}


@pytest.fixture(scope="module")
def recognizer(builtin_vocab: Vocabulary) -> DbowPlaceRecognizer:
    return DbowPlaceRecognizer(vocabulary_object=builtin_vocab)


@pytest.fixture(scope="module")
def long_loop() -> SyntheticDataset:
    """Texture seed 0: never seen in training (the built-in vocabulary uses seeds 1000, 1001)."""
    return SyntheticDataset(scene="long_loop", seed=0, imu=False)


def test_is_a_place_recognizer(recognizer: DbowPlaceRecognizer) -> None:
    assert isinstance(recognizer, PlaceRecognizer)


def test_transform_weights_and_direct_index(recognizer: DbowPlaceRecognizer, orb: FeatureExtractor) -> None:
    feats = orb.extract(SyntheticDataset(scene="room", seed=0, imu=False)[50].image)
    bow = recognizer.transform(feats.descriptors)
    assert sum(bow.words.values()) == pytest.approx(1.0) and min(bow.words.values()) > 0
    assert len(bow.words) > 500  # 1000 features spread over many of the 10,000 words
    idx = np.sort(np.concatenate(list(bow.direct_index.values())))
    assert np.array_equal(idx, np.unique(idx)) and idx.size <= len(feats)  # each feature in one node
    assert all(recognizer.vocabulary.depth[n] == 2 for n in bow.direct_index)
    assert recognizer.score(bow, bow) == pytest.approx(1.0)
    with pytest.raises(VocabularyError, match=r"descriptors must be \(N, 32\) uint8"):
        recognizer.transform(feats.descriptors[:, :16])


def test_unrelated_images_score_near_zero(recognizer: DbowPlaceRecognizer) -> None:
    rng = np.random.default_rng(0)
    a = recognizer.transform(rng.integers(0, 256, (1000, 32), dtype=np.uint8))
    b = recognizer.transform(rng.integers(0, 256, (1000, 32), dtype=np.uint8))
    # ~900 of the 10,000 words occur in each image, so chance overlap gives a floor of ~0.1 (ORBvoc's
    # 1M words give ~0.01); a revisited place scores > 0.5 (test below)
    assert recognizer.score(a, b) < 0.15
    assert recognizer.score(a, recognizer.transform(np.zeros((0, 32), np.uint8))) == 0.0


def _descriptors(ds: SyntheticDataset, orb: FeatureExtractor, frames: list[int]) -> list[NDArray[np.uint8]]:
    return [orb.extract(ds[i].image).descriptors for i in frames]


def test_same_place_scores_far_higher_than_other_places(
    recognizer: DbowPlaceRecognizer, long_loop: SyntheticDataset, orb: FeatureExtractor
) -> None:
    """Keyframes every 3 s around the whole loop; queries revisit places after one loop (70 s later, new
    image noise): the keyframe of the same place must come first, far above every other place."""
    fps, period = 30, 70.0
    kf_frames = list(range(0, int(period * fps), 3 * fps))
    db = DbowPlaceRecognizer(vocabulary_object=recognizer.vocabulary)
    for kf, d in enumerate(_descriptors(long_loop, orb, kf_frames)):
        db.add(kf, db.transform(d))
    query_frames = [int((period + t) * fps) for t in (0.0, 3.0, 6.0)]
    for q, d in zip(query_frames, _descriptors(long_loop, orb, query_frames), strict=True):
        ranked = db.query(db.transform(d))
        expected = (q - int(period * fps)) // (3 * fps)
        assert ranked[0][0] == expected
        assert ranked[0][1] > 0.5 and ranked[0][1] > 3 * ranked[1][1]


def test_bow_matching_two_views_agrees_with_ground_truth(
    recognizer: DbowPlaceRecognizer, orb: FeatureExtractor
) -> None:
    ds = SyntheticDataset(scene="room", seed=0, imu=False)
    f1, f2 = ds[120], ds[132]  # 0.4 s apart
    k1, k2 = orb.extract(f1.image), orb.extract(f2.image)
    b1, b2 = recognizer.transform(k1.descriptors), recognizer.transform(k2.descriptors)
    pairs = match_by_bow(k1, b1, k2, b2, ratio=0.75, **ORB_MATCHER)
    assert pairs.shape[1] == 2 and len(pairs) > 100
    assert np.unique(pairs[:, 0]).size == len(pairs) and np.unique(pairs[:, 1]).size == len(pairs)
    # ground truth: lift features of view 1 with the exact depth, project them into view 2
    assert f1.depth_m is not None and f1.T_w_c_gt is not None and f2.T_w_c_gt is not None
    uv1 = k1.uv_px[pairs[:, 0]].astype(np.float64)
    z = f1.depth_m[np.round(uv1[:, 1]).astype(int), np.round(uv1[:, 0]).astype(int)]
    K = ds.camera.K
    xyz1 = np.linalg.solve(K, np.vstack([uv1.T, np.ones(len(uv1))])).T * z[:, None]
    T_2_1 = np.linalg.inv(f2.T_w_c_gt) @ f1.T_w_c_gt
    xyz2 = xyz1 @ T_2_1[:3, :3].T + T_2_1[:3, 3]
    uv2 = (xyz2 @ K.T)[:, :2] / xyz2[:, 2:3]
    err = np.linalg.norm(uv2 - k2.uv_px[pairs[:, 1]], axis=1)
    tolerance = 3.0 * k2.level_scale()[pairs[:, 1]]
    assert np.mean(err < tolerance) > 0.95
    # the rotation check and the ratio test only remove matches
    loose = match_by_bow(k1, b1, k2, b2, ratio=1.0, max_distance=50, rotation_bins=None)
    assert len(loose) >= len(pairs)
    # masks restrict the features allowed to match
    mask = np.zeros(len(k1), bool)
    mask[: len(k1) // 2] = True
    masked = match_by_bow(k1, b1, k2, b2, 0.75, **ORB_MATCHER, mask1=mask)
    assert len(masked) > 0 and np.all(masked[:, 0] < len(k1) // 2)


def test_bow_matching_edge_cases(recognizer: DbowPlaceRecognizer, orb: FeatureExtractor) -> None:
    feats: Features = orb.extract(SyntheticDataset(scene="room", seed=0, imu=False)[10].image)
    bow = recognizer.transform(feats.descriptors)
    same = match_by_bow(feats, bow, feats, bow, 0.75, **ORB_MATCHER)
    assert np.array_equal(same[:, 0], same[:, 1])  # an image matches itself feature for feature
    empty = recognizer.transform(np.zeros((0, 32), np.uint8))
    assert match_by_bow(feats, bow, feats, empty, 0.75, **ORB_MATCHER).shape == (0, 2)
    with pytest.raises(VocabularyError, match=r"mask2 must be a \(\d+,\) bool array"):
        match_by_bow(feats, bow, feats, bow, 0.75, **ORB_MATCHER, mask2=np.ones(3, bool))


def _features(descriptors: NDArray[np.uint8]) -> Features:
    n = len(descriptors)
    zeros = np.zeros((n, 2), np.float32)
    return Features(
        zeros, zeros, np.zeros(n, np.int32), np.zeros(n, np.float32), np.zeros(n, np.float32), descriptors, 1.2, 8
    )


def test_node_pairs_are_the_close_allowed_pairs_of_shared_nodes() -> None:
    """SearchForTriangulation's FeatureVector walk on a hand-made direct index: shared nodes only, masked features
    left out, within the distance, in node order, then a, then b (the direct index's order)."""
    rng = np.random.default_rng(7)
    d1 = rng.integers(0, 256, (6, 32), dtype=np.uint8)
    d2 = rng.integers(0, 256, (7, 32), dtype=np.uint8)
    d2[1] = d1[0]  # distance 0
    d2[6] = d1[2] ^ np.uint8(1)  # distance 32 (one bit per byte)
    bow1 = BowDescription({}, {3: np.array([0, 2, 5]), 7: np.array([1]), 9: np.array([4])})
    bow2 = BowDescription({}, {3: np.array([1, 6, 5]), 7: np.array([0, 3]), 8: np.array([2])})
    f1, f2 = _features(d1), _features(d2)
    free1 = np.array([True, True, True, True, True, False])  # feature 5 of kf1 already has a point
    free2 = np.array([True, True, True, False, True, True, True])  # feature 3 of kf2 too
    a, b, d = node_pairs(f1, bow1, f2, bow2, free1, free2, 255)
    assert list(zip(a.tolist(), b.tolist(), strict=True)) == [(0, 1), (0, 6), (0, 5), (2, 1), (2, 6), (2, 5), (1, 0)]
    bits = np.unpackbits(d1[a] ^ d2[b], axis=1).sum(axis=1)
    np.testing.assert_array_equal(d, bits)
    a, b, d = node_pairs(f1, bow1, f2, bow2, free1, free2, 50)  # ORB-SLAM TH_LOW
    assert list(zip(a.tolist(), b.tolist(), d.tolist(), strict=True)) == [(0, 1, 0), (2, 6, 32)]
    a, _, _ = node_pairs(f1, bow1, f2, bow2, None, None, 255)  # no masks: feature 5 of kf1 pairs too
    assert a.tolist() == [0, 0, 0, 2, 2, 2, 5, 5, 5, 1, 1]
    with pytest.raises(VocabularyError, match=r"mask1 must be a \(6,\) bool array"):
        node_pairs(f1, bow1, f2, bow2, np.ones(3, bool), free2, 50)


def test_node_pairs_read_each_direct_index_of_its_own() -> None:
    """node_pairs reads the CSR arrays each bag of words carries: one made later (possibly at a freed address) gets
    its own pairs, and an earlier one still gives its own."""
    d = np.zeros((4, 32), np.uint8)
    f = _features(d)
    first = BowDescription({}, {1: np.array([0, 1])})
    assert node_pairs(f, first, f, first, None, None, 255)[0].tolist() == [0, 0, 1, 1]
    for k in range(40):
        other = BowDescription({}, {k: np.array([k % 4])})
        a, b, _ = node_pairs(f, other, f, other, None, None, 255)
        assert (a.tolist(), b.tolist()) == ([k % 4], [k % 4])
    assert node_pairs(f, first, f, first, None, None, 255)[1].tolist() == [0, 1, 0, 1]
