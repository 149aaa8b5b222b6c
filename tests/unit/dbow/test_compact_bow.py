"""Bags of words as arrays (issue 15: memory per keyframe): the same words, weights, direct index and scores as the
dicts of Python numbers they replace, bit for bit, in a fraction of the memory."""

from __future__ import annotations

import pickle
import tracemalloc

import numpy as np
import pytest
from numpy.typing import NDArray
from slamkit_dbow.database import KeyframeDatabase
from slamkit_dbow.vocabulary import Vocabulary

from slamkit.interfaces import BowDescription, DirectIndex, WordWeights


def _dict_transform(vocab: Vocabulary, descriptors: NDArray[np.uint8], level: int) -> tuple[dict, dict]:
    """The former representation, built as ``Vocabulary.transform`` built it before issue 15 (TF-IDF): words as a
    dict word -> weight in ascending word id, the direct index as a dict node -> int64 features."""
    wn = vocab.words_and_nodes(descriptors, level)
    idf = vocab.word_weights[wn.words]
    keep = np.flatnonzero(idf > 0)
    uniq, inverse = np.unique(wn.words[keep], return_inverse=True)
    values = np.bincount(inverse, weights=idf[keep], minlength=uniq.size).astype(np.float64)
    values = values / np.sum(np.abs(values))
    words = dict(zip(uniq.tolist(), values.tolist(), strict=True))
    nodes = wn.nodes[keep]
    direct: dict[int, list[int]] = {}
    for n, f in sorted(zip(nodes.tolist(), keep.tolist(), strict=True), key=lambda nf: nf[0]):
        direct.setdefault(n, []).append(f)
    return words, direct


def _dict_score(wa: dict[int, float], wb: dict[int, float]) -> float:
    """The former ``Vocabulary.score``: a Python loop over the smaller dict."""
    if len(wa) > len(wb):
        wa, wb = wb, wa
    s = 0.0
    for word, va in wa.items():
        vb = wb.get(word)
        if vb is not None:
            s += abs(va) + abs(vb) - abs(va - vb)
    return 0.5 * s


def test_transform_and_score_are_the_former_dicts_bit_for_bit(
    builtin_vocab: Vocabulary, room_descriptors: list[NDArray[np.uint8]]
) -> None:
    bows = [builtin_vocab.transform(d, 2) for d in room_descriptors]
    refs = [_dict_transform(builtin_vocab, d, 2) for d in room_descriptors]
    for bow, (words, direct) in zip(bows, refs, strict=True):
        assert isinstance(bow.words, WordWeights) and isinstance(bow.direct_index, DirectIndex)
        assert list(bow.words.items()) == list(words.items())  # same ids, same float64 weights, same order
        assert list(bow.direct_index) == list(direct)
        assert all(bow.direct_index[n].tolist() == f for n, f in direct.items())
    for i, (a, (wa, _)) in enumerate(zip(bows, refs, strict=True)):
        for b, (wb, _) in zip(bows[i:], refs[i:], strict=True):
            assert builtin_vocab.score(a, b) == _dict_score(wa, wb)  # exactly: same terms, same order
            assert builtin_vocab.score(b, a) == _dict_score(wa, wb)
    assert builtin_vocab.score(bows[0], bows[0]) == pytest.approx(1.0)


def test_a_bag_of_words_weighs_a_tenth_of_its_dicts(
    builtin_vocab: Vocabulary, room_descriptors: list[NDArray[np.uint8]]
) -> None:
    """What a keyframe keeps of its bag of words: measured by tracemalloc (Python and numpy allocations alive after
    the description is made), against the former dicts of the same image."""
    d = room_descriptors[0]
    assert d.shape[0] >= 900
    builtin_vocab.transform(d, 2)  # a first call may load compiled kernels (allocations that are not the result's)

    def retained(make: object) -> int:
        tracemalloc.start()
        before = tracemalloc.get_traced_memory()[0]
        kept = make()  # type: ignore[operator]
        after = tracemalloc.get_traced_memory()[0]
        tracemalloc.stop()
        assert kept is not None
        return after - before

    compact = retained(lambda: builtin_vocab.transform(d, 2))
    former = retained(lambda: _as_former_dicts(*_dict_transform(builtin_vocab, d, 2)))
    assert compact < 25_000, compact  # measured 17.9 KB: 12 bytes a word (~900), 4 a feature, 12 a node (~100)
    assert compact < former / 5, (compact, former)  # measured 164 KB


def _as_former_dicts(words: dict[int, float], direct: dict[int, list[int]]) -> tuple[dict, dict]:
    return words, {n: np.array(f, np.int64) for n, f in direct.items()}


def test_mappings_given_are_stored_as_sorted_arrays() -> None:
    bow = BowDescription({7: 0.25, 2: 0.5, 40: 0.25}, {9: np.array([4, 1]), 3: np.array([0])})
    w, di = bow.word_weights, bow.direct
    assert w.ids.dtype == np.int32 and w.ids.tolist() == [2, 7, 40] and w.weights.tolist() == [0.5, 0.25, 0.25]
    assert list(w.items()) == [(2, 0.5), (7, 0.25), (40, 0.25)] and w[7] == 0.25 and 7 in w and 8 not in w
    assert w == {2: 0.5, 7: 0.25, 40: 0.25} and len(w) == 3
    with pytest.raises(KeyError):
        _ = w[8]
    assert list(di) == [3, 9] and di[9].tolist() == [4, 1] and di.offsets.tolist() == [0, 1, 3]  # group order kept
    assert di.get(5) is None and 3 in di and len(di) == 2
    with pytest.raises(ValueError, match="read-only"):
        w.weights[0] = 1.0
    with pytest.raises(ValueError, match="read-only"):
        di.features[0] = 1
    again = pickle.loads(pickle.dumps(bow))
    assert list(again.words.items()) == list(bow.words.items()) and again.direct.features.tolist() == [0, 4, 1]
    assert BowDescription(bow.words, bow.direct_index).words is bow.words  # arrays are shared, not copied
    empty = BowDescription()
    assert len(empty.words) == 0 and len(empty.direct_index) == 0 and empty.direct.offsets.tolist() == [0]
    with pytest.raises(ValueError, match="ascending"):
        WordWeights(np.array([3, 1]), np.array([0.5, 0.5]))
    with pytest.raises(ValueError, match="offsets"):
        DirectIndex(np.array([1, 2]), np.array([0, 2]), np.array([0, 1]))


def test_inverted_index_lists_keep_the_insertion_order_of_an_ordered_set() -> None:
    """The inverted index as lists behaves as the dicts-as-ordered-sets it replaces: insertion order, removal, and a
    re-added keyframe goes to the end of each of its words' entries."""
    db = KeyframeDatabase(Vocabulary.score)
    for kf in (5, 3, 8):
        db.add(kf, BowDescription({1: 0.5, kf: 0.5}))
    assert db.keyframes_with_word(1) == [5, 3, 8]
    db.add(5, BowDescription({1: 1.0}))
    assert db.keyframes_with_word(1) == [3, 8, 5] and db.keyframes_with_word(5) == []
    db.remove(3)
    db.remove(3)
    assert db.keyframes_with_word(1) == [8, 5] and db.keyframes_with_word(3) == []
    assert db.common_words(BowDescription({1: 0.5, 8: 0.5})) == {8: 2, 5: 1}


def _numpy_search_by_bow(f1, bow1, f2, bow2, ratio, max_distance, rotation_bins, mask1, mask2):  # type: ignore[no-untyped-def]
    """The former ``match_by_bow``: per shared node, numpy's argmin and partition over the Hamming matrix."""
    from slamkit.pipeline.matching import hamming_matrix, resolve_one_to_one, rotation_consistent

    q_all, t_all, d_all = [], [], []
    for node, idx1 in bow1.direct_index.items():
        idx2 = bow2.direct_index.get(node)
        if idx2 is None:
            continue
        idx1, idx2 = np.asarray(idx1, np.int64), np.asarray(idx2, np.int64)
        idx1, idx2 = idx1[mask1[idx1]], idx2[mask2[idx2]]
        if idx1.size == 0 or idx2.size == 0:
            continue
        dist = hamming_matrix(f1.descriptors[idx1], f2.descriptors[idx2])
        best_j = np.argmin(dist, axis=1)
        best = dist[np.arange(idx1.size), best_j]
        second = np.full(idx1.size, np.inf)
        if idx2.size > 1:
            second = np.partition(dist, 1, axis=1)[:, 1].astype(np.float64)
        ok = (best <= max_distance) & (best < ratio * second)
        q_all.append(idx1[ok])
        t_all.append(idx2[best_j[ok]])
        d_all.append(best[ok])
    q, t, d = np.concatenate(q_all), np.concatenate(t_all), np.concatenate(d_all)
    keep = resolve_one_to_one(q, t, d)
    q, t = q[keep], t[keep]
    ok = rotation_consistent(f1.angle_deg[q].astype(np.float64) - f2.angle_deg[t].astype(np.float64), rotation_bins)
    q, t = q[ok], t[ok]
    order = np.argsort(q, kind="stable")
    return np.stack([q[order], t[order]], axis=1)


def test_search_by_bow_compiled_is_the_numpy_search(builtin_vocab: Vocabulary, orb: object) -> None:
    """match_by_bow's compiled per-node search gives exactly the pairs of the numpy search it replaced (nearest =
    first of equal distances, second = second smallest, lone candidates pass the ratio test), with and without
    masks, for SearchByBoW's ratios."""
    from slamkit_dbow.matching import match_by_bow

    from slamkit.io.synthetic.dataset import SyntheticDataset

    ds = SyntheticDataset(scene="room", seed=0, imu=False, depth=False)
    feats = [orb.extract(ds[i].image) for i in (40, 46, 70)]  # type: ignore[attr-defined]
    bows = [builtin_vocab.transform(f.descriptors, 2) for f in feats]
    rng = np.random.default_rng(1)
    n_checked = 0
    for a, b in ((0, 1), (1, 2), (0, 2)):
        for ratio in (0.6, 0.75, 0.9):
            for masked in (False, True):
                m1 = rng.random(len(feats[a])) < 0.6 if masked else np.ones(len(feats[a]), bool)
                m2 = rng.random(len(feats[b])) < 0.6 if masked else np.ones(len(feats[b]), bool)
                got = match_by_bow(
                    feats[a],
                    bows[a],
                    feats[b],
                    bows[b],
                    ratio,
                    50,
                    30,
                    mask1=m1 if masked else None,
                    mask2=m2 if masked else None,
                )
                want = _numpy_search_by_bow(feats[a], bows[a], feats[b], bows[b], ratio, 50, 30, m1, m2)
                assert np.array_equal(got, want), (a, b, ratio, masked)
                n_checked += got.shape[0]
    assert n_checked > 1000  # the views overlap: hundreds of matches per pair
