"""Vocabulary training: tree structure, k-means++ determinism, bitwise-majority centres, TF-IDF weights."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray
from slamkit_dbow.kernels import kmeans, kmeanspp_seeds, majority_centres
from slamkit_dbow.training import TrainingParams, train_vocabulary
from slamkit_dbow.vocabulary import Vocabulary

from slamkit.errors import ConfigError


def _bits_to_desc(bits: list[str]) -> NDArray[np.uint8]:
    """Descriptors (N, 8) uint8 from 64-character bit strings (bit i of the string = bit i of the row)."""
    rows = [np.packbits(np.array([int(c) for c in b], np.uint8), bitorder="little") for b in bits]
    return np.stack(rows)


def test_tree_structure(small_vocab: Vocabulary, room_descriptors: list[NDArray[np.uint8]]) -> None:
    v = small_vocab
    assert (v.k, v.L) == (6, 3)
    assert v.parent[0] == -1 and np.all(v.parent[1:] < np.arange(1, v.n_nodes))
    n_children = np.diff(v.child_start)
    assert n_children.max() <= 6 and n_children[0] == 6  # the root of 12k descriptors has k children
    assert np.all((n_children == 0) == v.is_leaf)
    assert v.depth.max() == 3 and np.all(v.depth[v.is_leaf] >= 1)
    # a full tree here: 12k descriptors are plenty for 6^3 = 216 leaves
    assert v.n_words == 216 and v.n_nodes == 1 + 6 + 36 + 216
    # children of a node are consecutive ids (created together), level by level
    for node in range(v.n_nodes):
        kids = v.children[v.child_start[node] : v.child_start[node + 1]]
        assert np.array_equal(kids, np.arange(kids[0], kids[0] + kids.size)) if kids.size else True
    # internal nodes weigh 0; words weigh ln(N / N_i) with N = 12 images
    assert np.all(v.weights[~v.is_leaf] == 0)
    ws = v.word_weights
    assert np.all(ws >= 0) and ws.max() <= np.log(12) + 1e-12
    assert np.allclose(np.exp(-ws) * 12, np.round(np.exp(-ws) * 12))  # N_i = 12 exp(-w) is an integer


def test_every_word_is_reached_by_training_data(
    small_vocab: Vocabulary, room_descriptors: list[NDArray[np.uint8]]
) -> None:
    words = small_vocab.words_and_nodes(np.concatenate(room_descriptors), 0).words
    assert np.unique(words).size == small_vocab.n_words


def test_idf_counts_documents_not_features() -> None:
    # image 0 holds word A three times, image 1 holds word B once, image 2 holds A and B
    a, b = np.zeros((1, 32), np.uint8), np.full((1, 32), 255, np.uint8)
    imgs = [np.concatenate([a, a, a]), b, np.concatenate([a, b])]
    v = train_vocabulary(imgs, TrainingParams(k=2, L=1))
    assert v.n_words == 2
    assert np.allclose(sorted(v.word_weights), [np.log(3 / 2), np.log(3 / 2)])
    bow = v.transform(imgs[0], 1)
    assert len(bow.words) == 1 and np.isclose(next(iter(bow.words.values())), 1.0)


def test_training_is_deterministic_and_seed_dependent(room_descriptors: list[NDArray[np.uint8]]) -> None:
    data = room_descriptors[:4]
    v1 = train_vocabulary(data, TrainingParams(k=5, L=2, seed=7, n_threads=1))
    v2 = train_vocabulary(data, TrainingParams(k=5, L=2, seed=7, n_threads=2))
    v3 = train_vocabulary(data, TrainingParams(k=5, L=2, seed=8))
    assert v1.same_as(v2)  # same seed, any thread count: the same tree
    assert not v1.same_as(v3)


def test_kmeanspp_seeds_deterministic_distinct_and_spread() -> None:
    rng = np.random.default_rng(0)
    # 3 tight clusters of 64-bit descriptors around far-apart centres
    centres = rng.integers(0, 256, (3, 8), dtype=np.uint8)
    desc = np.repeat(centres, 50, axis=0)
    flips = rng.integers(0, 64, 150)
    for i, f in enumerate(flips):
        desc[i, f // 8] ^= np.uint8(1 << (f % 8))
    d64 = desc.view(np.uint64)
    u = rng.random(3)
    s1 = kmeanspp_seeds(d64, 3, 10, u)
    s2 = kmeanspp_seeds(d64, 3, 10, u)
    assert np.array_equal(s1, s2) and s1[0] == 10
    assert sorted(int(i) // 50 for i in s1) == [0, 1, 2]  # D^2 sampling lands one seed in each cluster
    # fewer distinct descriptors than k: seeding stops early
    assert kmeanspp_seeds(np.repeat(d64[:1], 5, axis=0), 3, 0, u).size == 1


def test_majority_centres_exact() -> None:
    desc = _bits_to_desc(
        [
            "1100" + "0" * 60,
            "1010" + "0" * 60,
            "1001" + "0" * 60,
            "0111" + "1" * 60,  # cluster 1 alone
        ]
    )
    assign = np.array([0, 0, 0, 1], np.int32)
    c = majority_centres(desc.view(np.uint64), assign, 3).view(np.uint8)
    assert np.array_equal(c[0], _bits_to_desc(["1000" + "0" * 60])[0])  # bit 0 in 3/3, others 1/3
    assert np.array_equal(c[1], desc[3])
    assert not c[2].any()  # empty cluster
    # a tie (2 of 4) sets the bit, as DBoW2's FORB::meanValue
    tie = _bits_to_desc(["1" + "0" * 63, "1" + "0" * 63, "0" * 64, "0" * 64])
    ct = majority_centres(tie.view(np.uint64), np.zeros(4, np.int32), 1).view(np.uint8)
    assert ct[0, 0] == 1 and not ct[0, 1:].any()


def test_kmeans_converges_to_the_clusters() -> None:
    rng = np.random.default_rng(1)
    centres = rng.integers(0, 256, (4, 32), dtype=np.uint8)
    desc = np.repeat(centres, 30, axis=0)
    for i in range(desc.shape[0]):  # flip 5 random bits of every copy
        for f in rng.choice(256, 5, replace=False):
            desc[i, f // 8] ^= np.uint8(1 << (f % 8))
    out, assign, iterations = kmeans(desc.view(np.uint64), 4, 0, rng.random(4), 50)
    assert out.shape == (4, 4) and 1 <= iterations < 50
    truth = np.repeat(np.arange(4), 30)
    for c in range(4):  # each found cluster is exactly one true cluster, whose centre it recovers
        members = truth[assign == c]
        assert members.size == 30 and np.all(members == members[0])
        assert np.array_equal(out[c : c + 1].view(np.uint8)[0], centres[members[0]])


def test_small_groups_make_one_child_per_distinct_descriptor() -> None:
    a = np.arange(32, dtype=np.uint8)[None]
    b = a.copy()
    b[0, 0] = 255
    v = train_vocabulary([np.concatenate([a, b, a])], TrainingParams(k=10, L=3))
    assert v.n_words == 2 and v.n_nodes == 3  # duplicates do not grow chains or duplicate words
    assert np.array_equal(v.descriptors[1], a[0]) and np.array_equal(v.descriptors[2], b[0])


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"k": 1}, "k must be"),
        ({"L": 0}, "L must be"),
        ({"k": 100, "L": 5}, "too many"),
        ({"n_threads": 0}, "n_threads"),
    ],
)
def test_bad_training_params(kwargs: dict[str, int], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        TrainingParams(**kwargs)


def test_training_needs_descriptors() -> None:
    with pytest.raises(ConfigError, match="no descriptors"):
        train_vocabulary([np.zeros((0, 32), np.uint8)])
    with pytest.raises(ConfigError, match="multiple of 8"):
        train_vocabulary([np.zeros((3, 5), np.uint8)])
