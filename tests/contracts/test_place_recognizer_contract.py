"""The PlaceRecognizer contract: every registered place recognizer must pass these tests.

Parametrized over ``ComponentRegistry.discover().components("place")``, each built from its default config node
(a fresh database per test). Features come from the default extractor (``features=orb``) on frames of slamkit's
synthetic room: eight places 100 frames (3.3 s) apart, and for each a second view 3 frames later.

What a place recognizer promises (slamkit/interfaces.py PlaceRecognizer, ORB-SLAM III-E, V-C, VII-A):
- ``transform`` is deterministic; its words are L1-normalised positive weights; its direct index (if it has one)
  lists each feature at most once, within range;
- ``score(a, a) = 1``, scores are symmetric and in [0, 1], and a second view of a place scores higher with it than
  the other places do (median);
- a keyframe added is its own best query result (score 1); ``exclude`` leaves it out; after ``remove`` no query
  returns it;
- ``loop_candidates`` never returns a connected keyframe, only keyframes scoring at least ``min_score`` with the
  query, and finds the place a second view was taken at; ``relocalization_candidates`` finds it too;
- ``match`` returns (K, 2) int64 one-to-one index pairs within range, within ``max_distance`` bits, restricted by
  the masks, and on an image and its copy shifted by (9, -6) px at least 90 % of more than 100 pairs are correct
  (the shift within 2 px x the level's scale); a looser ratio and no rotation check give at least as many pairs;
- ``candidate_pairs`` (local mapping's triangulation candidates, ORB-SLAM SearchForTriangulation) returns each
  pair once as (a, b, distance) int64 arrays, within range, restricted by the masks, with the pair's true Hamming
  distance <= ``max_distance``, the same on every call; every pair ``match`` finds under the same masks and
  distance is among them; on an image and its shifted copy it keeps at least half of the true correspondences
  within ``max_distance`` (a recognizer with no structure returns every close pair: all of them).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import pytest

from slamkit.features import Features
from slamkit.interfaces import BowDescription, FeatureExtractor, PlaceRecognizer
from slamkit.io.synthetic.dataset import SyntheticDataset
from slamkit.pipeline.config import MatcherConfig
from slamkit.pipeline.matching import close_pairs, hamming_rows
from slamkit.plugins import ComponentRegistry

REGISTRY = ComponentRegistry.discover()
NAMES = [c.spec.name for c in REGISTRY.components("place")]
PLACES = list(range(0, 800, 100))
SECOND_VIEW = 3  # frames after each place
SHIFT = (9, -6)  # px, (du, dv) of the shifted copy
MATCHER = MatcherConfig()
ORB = {"max_distance": MATCHER.th_low, "rotation_bins": MATCHER.rotation_bins}


@dataclass(frozen=True)
class View:
    image: np.ndarray
    features: Features
    bow: BowDescription


@pytest.fixture(scope="module")
def extractor() -> FeatureExtractor:
    built: FeatureExtractor = REGISTRY.instantiate("features", REGISTRY.get("features", "orb").config_node())
    return built


@pytest.fixture(params=NAMES)
def recognizer(request: pytest.FixtureRequest) -> PlaceRecognizer:
    built: PlaceRecognizer = REGISTRY.instantiate("place", REGISTRY.get("place", request.param).config_node())
    return built


@pytest.fixture(scope="module")
def images() -> dict[int, np.ndarray]:
    room = SyntheticDataset(scene="room", seed=0, imu=False)
    return {i: np.asarray(room[i].image) for k in PLACES for i in (k, k + SECOND_VIEW)}


def views(recognizer: PlaceRecognizer, extractor: FeatureExtractor, images: dict[int, np.ndarray]) -> dict[int, View]:
    out = {}
    for i, image in images.items():
        feats = extractor.extract(image)
        out[i] = View(image, feats, recognizer.transform(feats.descriptors))
    return out


@pytest.fixture
def room_views(
    recognizer: PlaceRecognizer, extractor: FeatureExtractor, images: dict[int, np.ndarray]
) -> dict[int, View]:
    return views(recognizer, extractor, images)


def shifted(image: np.ndarray) -> np.ndarray:
    M = np.array([[1, 0, SHIFT[0]], [0, 1, SHIFT[1]]], np.float64)
    return np.asarray(cv2.warpAffine(image, M, (image.shape[1], image.shape[0]), borderMode=cv2.BORDER_REPLICATE))


def no_neighbors(_kf: int, _n: int) -> list[int]:
    return []


# ---- checks (also run on broken recognizers below) -----------------------------------------------------------


def check_scores(recognizer: PlaceRecognizer, vs: dict[int, View]) -> None:
    for k in PLACES:
        a = vs[k].bow
        assert recognizer.score(a, a) == pytest.approx(1.0, abs=1e-9)
        others = [recognizer.score(a, vs[j].bow) for j in PLACES if j != k]
        for j in PLACES:
            s = recognizer.score(a, vs[j].bow)
            assert 0.0 <= s <= 1.0 + 1e-12
            assert s == pytest.approx(recognizer.score(vs[j].bow, a), abs=1e-12)
        assert recognizer.score(a, vs[k + SECOND_VIEW].bow) > np.median(others), f"place {k}"


def check_match(recognizer: PlaceRecognizer, extractor: FeatureExtractor, image: np.ndarray) -> None:
    f1 = extractor.extract(image)
    f2 = extractor.extract(shifted(image))
    b1, b2 = recognizer.transform(f1.descriptors), recognizer.transform(f2.descriptors)
    pairs = recognizer.match(f1, b1, f2, b2, 0.75, None, None, **ORB)
    assert pairs.ndim == 2 and pairs.shape[1] == 2 and pairs.dtype == np.int64
    assert pairs.shape[0] > 100, pairs.shape
    assert np.all((pairs[:, 0] >= 0) & (pairs[:, 0] < len(f1)) & (pairs[:, 1] >= 0) & (pairs[:, 1] < len(f2)))
    assert np.unique(pairs[:, 0]).size == len(pairs) and np.unique(pairs[:, 1]).size == len(pairs), "one-to-one"
    bits = hamming_rows(f1.descriptors[pairs[:, 0]], f2.descriptors[pairs[:, 1]])
    assert bits.max() <= MATCHER.th_low
    err = np.linalg.norm(f2.uv_px[pairs[:, 1]] - (f1.uv_px[pairs[:, 0]] + np.array(SHIFT, np.float32)), axis=1)
    correct = err <= 2.0 * f1.level_scale()[pairs[:, 0]]
    assert correct.mean() >= 0.9, f"{correct.mean():.2f} of {len(pairs)} pairs correct"
    tight = recognizer.match(f1, b1, f2, b2, 0.75, None, None, max_distance=10, rotation_bins=MATCHER.rotation_bins)
    assert tight.shape[0] < pairs.shape[0]
    if tight.size:
        assert hamming_rows(f1.descriptors[tight[:, 0]], f2.descriptors[tight[:, 1]]).max() <= 10
    loose = recognizer.match(f1, b1, f2, b2, 1.0, None, None, max_distance=MATCHER.th_low, rotation_bins=None)
    assert loose.shape[0] >= pairs.shape[0]
    mask1 = np.zeros(len(f1), bool)
    mask1[::2] = True
    mask2 = np.zeros(len(f2), bool)
    mask2[: len(f2) // 2] = True
    masked = recognizer.match(f1, b1, f2, b2, 0.75, mask1, mask2, **ORB)
    assert masked.shape[0] > 0 and mask1[masked[:, 0]].all() and mask2[masked[:, 1]].all()


def check_candidate_pairs(recognizer: PlaceRecognizer, extractor: FeatureExtractor, image: np.ndarray) -> None:
    f1 = extractor.extract(image)
    f2 = extractor.extract(shifted(image))
    b1, b2 = recognizer.transform(f1.descriptors), recognizer.transform(f2.descriptors)
    th = MATCHER.th_low
    mask1 = np.zeros(len(f1), bool)
    mask1[::2] = True
    mask2 = np.zeros(len(f2), bool)
    mask2[: len(f2) // 2] = True
    for m1, m2 in ((None, None), (mask1, mask2)):
        a, b, d = recognizer.candidate_pairs(f1, b1, f2, b2, m1, m2, max_distance=th)
        assert all(x.dtype == np.int64 and x.ndim == 1 for x in (a, b, d)) and a.size == b.size == d.size
        assert a.size > 0
        assert np.all((a >= 0) & (a < len(f1)) & (b >= 0) & (b < len(f2)))
        if m1 is not None and m2 is not None:
            assert m1[a].all() and m2[b].all(), "restricted by the masks"
        np.testing.assert_array_equal(d, hamming_rows(f1.descriptors[a], f2.descriptors[b]))
        assert d.max() <= th
        pairs = set(zip(a.tolist(), b.tolist(), strict=True))
        assert len(pairs) == a.size, "each pair once"
        again = recognizer.candidate_pairs(f1, b1, f2, b2, m1, m2, max_distance=th)
        assert all(np.array_equal(x, y) for x, y in zip((a, b, d), again, strict=True)), "deterministic"
        matched = recognizer.match(f1, b1, f2, b2, 1.0, m1, m2, max_distance=th, rotation_bins=None)
        assert set(map(tuple, matched.tolist())) <= pairs, "a pair match finds is a candidate"
        if m1 is None:
            # the true correspondences within the distance: most are candidates
            ta, tb, _ = close_pairs(f1.descriptors, f2.descriptors, np.ones(len(f1), bool), np.ones(len(f2), bool), th)
            err = np.linalg.norm(f2.uv_px[tb] - (f1.uv_px[ta] + np.array(SHIFT, np.float32)), axis=1)
            true = (err <= 2.0 * f1.level_scale()[ta]) & (f1.level[ta] == f2.level[tb])
            found = np.array([(x, y) in pairs for x, y in zip(ta[true].tolist(), tb[true].tolist(), strict=True)])
            assert true.sum() > 100 and found.mean() >= 0.5, f"{found.mean():.2f} of {true.sum()} true pairs"


# ---- the contract ----------------------------------------------------------------------------------------------


def test_is_a_place_recognizer(recognizer: PlaceRecognizer) -> None:
    assert isinstance(recognizer, PlaceRecognizer)


def test_transform_is_deterministic_and_well_formed(recognizer: PlaceRecognizer, room_views: dict[int, View]) -> None:
    for k in PLACES[:3]:
        v = room_views[k]
        again = recognizer.transform(v.features.descriptors.copy())
        assert dict(again.words) == dict(v.bow.words)
        weights = np.array(list(v.bow.words.values()))
        assert weights.size > 0 and np.all(weights > 0) and weights.sum() == pytest.approx(1.0, abs=1e-9)
        if v.bow.direct_index:  # the recognizer's own structure, if it has one
            indices = np.concatenate([np.asarray(ix).ravel() for ix in v.bow.direct_index.values()])
            assert np.unique(indices).size == indices.size, "a feature in two direct-index nodes"
            assert indices.min() >= 0 and indices.max() < len(v.features)
    empty = recognizer.transform(np.zeros((0, 32), np.uint8))
    assert len(empty.words) == 0


def test_scores(recognizer: PlaceRecognizer, room_views: dict[int, View]) -> None:
    check_scores(recognizer, room_views)


def test_added_keyframe_is_its_own_best_result_until_removed(
    recognizer: PlaceRecognizer, room_views: dict[int, View]
) -> None:
    ids = {k: 1000 + n for n, k in enumerate(PLACES)}
    for k, kf in ids.items():
        recognizer.add(kf, room_views[k].bow)
    for k, kf in ids.items():
        results = recognizer.query(room_views[k].bow)
        assert results[0][0] == kf and results[0][1] == pytest.approx(1.0, abs=1e-9)
        scores = [s for _, s in results]
        assert scores == sorted(scores, reverse=True), "best first"
        assert kf not in [i for i, _ in recognizer.query(room_views[k].bow, exclude=[kf])]
    gone = ids[PLACES[2]]
    recognizer.remove(gone)
    for k in PLACES:
        assert gone not in [i for i, _ in recognizer.query(room_views[k].bow)]


def test_loop_candidates(recognizer: PlaceRecognizer, room_views: dict[int, View]) -> None:
    ids = {k: 1000 + n for n, k in enumerate(PLACES)}
    for k, kf in ids.items():
        recognizer.add(kf, room_views[k].bow)
    by_id = {kf: room_views[k].bow for k, kf in ids.items()}
    for k in PLACES:
        query = room_views[k + SECOND_VIEW].bow
        found = recognizer.loop_candidates(query, set(), 0.0, no_neighbors)
        assert found and found[0][0] == ids[k], f"the second view of place {k} finds {found[:3]}"
        reloc = recognizer.relocalization_candidates(query, no_neighbors)
        assert reloc and reloc[0][0] == ids[k]
        # connected keyframes are never candidates
        connected = {ids[k], ids[PLACES[(PLACES.index(k) + 1) % len(PLACES)]]}
        assert not connected & {i for i, _ in recognizer.loop_candidates(query, connected, 0.0, no_neighbors)}
        # every candidate scores at least min_score with the query
        own = sorted(recognizer.score(query, b) for b in by_id.values())
        min_score = own[len(own) // 2]
        for kf, _ in recognizer.loop_candidates(query, set(), min_score, no_neighbors):
            assert recognizer.score(query, by_id[kf]) >= min_score
        assert recognizer.loop_candidates(query, set(), 1.0 + 1e-9, no_neighbors) == []


def test_match(recognizer: PlaceRecognizer, extractor: FeatureExtractor, images: dict[int, np.ndarray]) -> None:
    check_match(recognizer, extractor, images[PLACES[1]])


def test_candidate_pairs(
    recognizer: PlaceRecognizer, extractor: FeatureExtractor, images: dict[int, np.ndarray]
) -> None:
    check_candidate_pairs(recognizer, extractor, images[PLACES[1]])


# ---- the suite catches a broken recognizer ---------------------------------------------------------------------


class _Broken:
    """Delegates to a real recognizer, with one method replaced."""

    def __init__(self, inner: PlaceRecognizer, **replaced: Callable[..., Any]) -> None:
        self._inner = inner
        self.__dict__.update(replaced)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)


def test_suite_fails_on_broken_recognizers(extractor: FeatureExtractor, images: dict[int, np.ndarray]) -> None:
    inner = REGISTRY.instantiate("place", REGISTRY.get("place", "dbow").config_node())
    vs = views(inner, extractor, images)
    damped = _Broken(inner, score=lambda a, b: 0.9 * inner.score(a, b))
    with pytest.raises(AssertionError):
        check_scores(damped, vs)

    def scrambled(*args: Any, **kwargs: Any) -> np.ndarray:
        pairs = inner.match(*args, **kwargs)
        return np.stack([pairs[:, 0], np.roll(pairs[:, 1], 1)], axis=1)  # still one-to-one, mostly wrong

    with pytest.raises(AssertionError):
        check_match(_Broken(inner, match=scrambled), extractor, images[PLACES[1]])

    def unmasked(
        f1: Features, b1: BowDescription, f2: Features, b2: BowDescription, ratio: float, *_: Any, **kw: Any
    ) -> np.ndarray:
        return inner.match(f1, b1, f2, b2, ratio, None, None, **kw)  # ignores the masks

    with pytest.raises(AssertionError):
        check_match(_Broken(inner, match=unmasked), extractor, images[PLACES[1]])

    def candidates_unmasked(
        f1: Features, b1: BowDescription, f2: Features, b2: BowDescription, *_: Any, **kw: Any
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return inner.candidate_pairs(f1, b1, f2, b2, None, None, **kw)  # ignores the masks

    def candidates_halved(*args: Any, **kwargs: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        a, b, d = inner.candidate_pairs(*args, **kwargs)
        return a[::2], b[::2], d[::2]  # loses pairs match would find

    def candidates_unbounded(*args: Any, **kwargs: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return inner.candidate_pairs(*args, **{**kwargs, "max_distance": 256})  # ignores the distance bound

    for broken in (candidates_unmasked, candidates_halved, candidates_unbounded):
        with pytest.raises(AssertionError):
            check_candidate_pairs(_Broken(inner, candidate_pairs=broken), extractor, images[PLACES[1]])

    def every_close_pair(
        f1: Features, b1: BowDescription, f2: Features, b2: BowDescription, m1: Any, m2: Any, *, max_distance: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ones1, ones2 = np.ones(len(f1), bool), np.ones(len(f2), bool)
        return close_pairs(
            f1.descriptors, f2.descriptors, ones1 if m1 is None else m1, ones2 if m2 is None else m2, max_distance
        )

    # the documented fallback of a recognizer without a vocabulary structure passes
    check_candidate_pairs(_Broken(inner, candidate_pairs=every_close_pair), extractor, images[PLACES[1]])
