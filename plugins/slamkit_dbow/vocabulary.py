"""A DBoW2 vocabulary: a tree of binary descriptors whose leaves are the visual words.

Nodes are numbered as in DBoW2 (and in the lines of its text format): node 0 is the root, every other
node's parent has a smaller id, and the children of a node are ordered by id. Words are the leaves,
numbered in node-id order (DBoW2's ``createWords`` / ``loadFromTextFile``). Each word carries its IDF
weight ln(N / N_i) (TF-IDF weighting); internal nodes have weight 0.

``transform`` turns an image's descriptors into its bag of words (L1-normalised TF-IDF vector) and its
direct index (the image's features grouped by the node they cross at ``direct_index_level``), exactly as
DBoW2's ``transform(features, v, fv, levelsup)``; ``score`` is DBoW2's L1 score.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slamkit.errors import SlamkitError
from slamkit.interfaces import BowDescription, DirectIndex, WordWeights
from slamkit_dbow.kernels import descend, l1_common_sum


class Scoring(IntEnum):
    """DBoW2's ScoringType (the 3rd number of the text header). slamkit implements L1_NORM (ORB-SLAM's)."""

    L1_NORM = 0
    L2_NORM = 1
    CHI_SQUARE = 2
    KL = 3
    BHATTACHARYYA = 4
    DOT_PRODUCT = 5


class Weighting(IntEnum):
    """DBoW2's WeightingType (the 4th number of the text header)."""

    TF_IDF = 0
    TF = 1
    IDF = 2
    BINARY = 3


class VocabularyError(SlamkitError, ValueError):
    """A malformed vocabulary, or input (descriptors, feature masks) that does not fit it."""


@dataclass(frozen=True)
class WordsAndNodes:
    """Per-feature result of descending the tree: word (N,) int32 and node at the direct-index level (N,)."""

    words: NDArray[np.int32]
    nodes: NDArray[np.int32]


class Vocabulary:
    """A vocabulary tree of binary descriptors.

    k: branching factor; L: depth (levels below the root); scoring / weighting: DBoW2's codes.
    parent: (n_nodes,) int32 parent id of each node (-1 for the root, node 0).
    descriptors: (n_nodes, D) uint8 node centres (the root's row is unused, zeros); D a multiple of 8.
    weights: (n_nodes,) float64, the IDF weight of each word (0 for internal nodes; a word of weight 0 is
        "stopped": transform drops the features that reach it, as DBoW2).
    is_leaf: (n_nodes,) bool, True for words. A leaf has no children and every internal node has some.
    metadata: free-form provenance (training recipe), kept by the binary format.
    """

    def __init__(
        self,
        k: int,
        L: int,
        parent: NDArray[np.integer],
        descriptors: NDArray[np.uint8],
        weights: NDArray[np.floating],
        is_leaf: NDArray[np.bool_],
        scoring: int = Scoring.L1_NORM,
        weighting: int = Weighting.TF_IDF,
        metadata: Mapping[str, Any] | None = None,
    ) -> None:
        self.k = int(k)
        self.L = int(L)
        self.scoring = Scoring(int(scoring))
        self.weighting = Weighting(int(weighting))
        self.parent = np.ascontiguousarray(parent, np.int32)
        self.descriptors = np.ascontiguousarray(descriptors, np.uint8)
        self.weights = np.ascontiguousarray(weights, np.float64)
        self.is_leaf = np.ascontiguousarray(is_leaf, np.bool_)
        self.metadata: dict[str, Any] = dict(metadata or {})
        self._validate()
        n = self.n_nodes
        # children in CSR form, ordered by id (parents precede children, so a stable sort by parent suffices)
        child_ids = np.arange(1, n, dtype=np.int32)
        order = np.argsort(self.parent[1:], kind="stable")
        self.children = np.ascontiguousarray(child_ids[order], np.int32)
        counts = np.bincount(self.parent[1:], minlength=n)
        self.child_start = np.zeros(n + 1, np.int64)
        np.cumsum(counts, out=self.child_start[1:])
        if np.any((counts > 0) == self.is_leaf):
            bad = int(np.flatnonzero((counts > 0) == self.is_leaf)[0])
            what = "is flagged a leaf but has children" if self.is_leaf[bad] else "is not a leaf but has no children"
            raise VocabularyError(f"vocabulary node {bad} {what}")
        self.word_nodes = np.flatnonzero(self.is_leaf).astype(np.int32)
        self.word_of_node = np.full(n, -1, np.int32)
        self.word_of_node[self.word_nodes] = np.arange(self.word_nodes.size, dtype=np.int32)
        self.word_weights = self.weights[self.word_nodes].copy()
        depth = np.zeros(n, np.int32)
        up = np.arange(n)
        while np.any(up > 0):  # climb every node one level per pass (as many passes as the tree is deep)
            depth += up > 0
            up = np.where(up > 0, self.parent[up], 0)
        self.depth = depth
        self._desc64 = self.descriptors.view(np.uint64)

    def _validate(self) -> None:
        n = self.parent.shape[0]
        if n < 2:
            raise VocabularyError("a vocabulary needs a root and at least one word")
        if self.descriptors.ndim != 2 or self.descriptors.shape[0] != n or self.descriptors.shape[1] % 8:
            raise VocabularyError(
                f"vocabulary descriptors must be ({n}, D) uint8 with D a multiple of 8, got {self.descriptors.shape}"
            )
        if self.weights.shape != (n,) or self.is_leaf.shape != (n,):
            raise VocabularyError(f"vocabulary weights/is_leaf must have {n} entries")
        if self.parent[0] != -1:
            raise VocabularyError(f"vocabulary node 0 must be the root (parent -1), got parent {self.parent[0]}")
        ids = np.arange(n)
        bad = np.flatnonzero((self.parent[1:] < 0) | (self.parent[1:] >= ids[1:]))
        if bad.size:
            i = int(bad[0]) + 1
            raise VocabularyError(f"vocabulary node {i} has parent {self.parent[i]}: expected an id in [0, {i})")
        if not np.all(np.isfinite(self.weights)) or np.any(self.weights < 0):
            raise VocabularyError("vocabulary weights must be finite and >= 0")
        if self.is_leaf[0]:
            raise VocabularyError("vocabulary root (node 0) cannot be a word")
        if self.k < 1 or self.L < 1:
            raise VocabularyError(f"vocabulary k and L must be >= 1, got k={self.k}, L={self.L}")

    # ---- sizes ----------------------------------------------------------------------------------

    @property
    def n_nodes(self) -> int:
        """Number of nodes including the root."""
        return int(self.parent.shape[0])

    @property
    def n_words(self) -> int:
        return int(self.word_nodes.shape[0])

    @property
    def descriptor_bytes(self) -> int:
        return int(self.descriptors.shape[1])

    def __repr__(self) -> str:
        return (
            f"Vocabulary(k={self.k}, L={self.L}, words={self.n_words}, nodes={self.n_nodes}, "
            f"scoring={self.scoring.name}, weighting={self.weighting.name})"
        )

    def same_as(self, other: Vocabulary) -> bool:
        """True when both trees are identical (structure, centres, weights, k, L, scoring, weighting)."""
        return (
            (self.k, self.L, self.scoring, self.weighting) == (other.k, other.L, other.scoring, other.weighting)
            and np.array_equal(self.parent, other.parent)
            and np.array_equal(self.descriptors, other.descriptors)
            and np.array_equal(self.weights, other.weights)
            and np.array_equal(self.is_leaf, other.is_leaf)
        )

    def identity(self) -> dict[str, Any]:
        """What a saved map records of the vocabulary its bags of words come from (slamkit/map/mapfile.py): sha256
        over exactly what ``same_as`` compares (k, L, scoring, weighting, parents, centres, weights, leaf flags), and
        its sizes. Two vocabularies have the same identity iff ``same_as`` (up to a hash collision). Cached."""
        cached: dict[str, Any] | None = getattr(self, "_identity", None)
        if cached is None:
            h = hashlib.sha256()
            h.update(f"dbow2 k={self.k} L={self.L} {self.scoring.name} {self.weighting.name};".encode())
            for array in (self.parent, self.descriptors, self.weights, self.is_leaf):
                h.update(f"{array.dtype.str}{array.shape};".encode())
                h.update(np.ascontiguousarray(array).tobytes())
            cached = {"kind": "dbow2", "sha256": h.hexdigest(), "words": self.n_words, "nodes": self.n_nodes}
            self._identity = cached
        return dict(cached)

    # ---- transform ------------------------------------------------------------------------------

    def _check_descriptors(self, descriptors: NDArray[np.uint8]) -> NDArray[np.uint8]:
        d = np.asarray(descriptors)
        if d.dtype != np.uint8 or d.ndim != 2 or d.shape[1] != self.descriptor_bytes:
            raise VocabularyError(
                f"descriptors must be (N, {self.descriptor_bytes}) uint8 for this vocabulary, "
                f"got shape {d.shape} dtype {d.dtype}"
            )
        return np.ascontiguousarray(d)

    def words_and_nodes(self, descriptors: NDArray[np.uint8], direct_index_level: int) -> WordsAndNodes:
        """descriptors: (N, D) uint8 -> each one's word and its node at depth ``direct_index_level``."""
        d = self._check_descriptors(descriptors)
        words, nodes = descend(
            d.view(np.uint64), self._desc64, self.child_start, self.children, self.word_of_node, direct_index_level
        )
        return WordsAndNodes(words, nodes)

    def transform(self, descriptors: NDArray[np.uint8], direct_index_level: int) -> BowDescription:
        """descriptors: (N, D) uint8 of one image -> its bag of words and direct index.

        words: word id -> weight, L1-normalised (sum 1), as arrays (``WordWeights``: ascending word id). TF-IDF/TF: a word's weight is the sum of its idf
        over the image's features that reach it; IDF/BINARY: its idf once. Features reaching a stopped
        word (weight 0) are left out of both. direct_index: node id at depth ``direct_index_level`` (0 =
        root) -> (n,) int32 feature indices, ascending, as CSR arrays (``DirectIndex``: ascending node id).
        """
        if self.scoring != Scoring.L1_NORM:
            raise VocabularyError(f"scoring {self.scoring.name} is not supported; slamkit implements L1_NORM")
        wn = self.words_and_nodes(descriptors, direct_index_level)
        idf = self.word_weights[wn.words]
        keep = np.flatnonzero(idf > 0)
        if keep.size == 0:
            return BowDescription()
        w = wn.words[keep]
        uniq, inverse = np.unique(w, return_inverse=True)
        if self.weighting in (Weighting.TF_IDF, Weighting.TF):
            per_feature = idf[keep] if self.weighting == Weighting.TF_IDF else np.ones(keep.size)
            values = np.bincount(inverse, weights=per_feature, minlength=uniq.size).astype(np.float64)
        else:
            values = np.asarray(
                self.word_weights[uniq] if self.weighting == Weighting.IDF else np.ones(uniq.size), np.float64
            )
        values = values / np.sum(np.abs(values))
        nodes = wn.nodes[keep]
        order = np.argsort(nodes, kind="stable")
        sorted_nodes = nodes[order]
        starts = np.flatnonzero(np.diff(sorted_nodes)) + 1
        offsets = np.concatenate(([0], starts, [sorted_nodes.size])).astype(np.int64)
        direct = DirectIndex(sorted_nodes[offsets[:-1]], offsets, keep[order])
        return BowDescription(WordWeights(uniq, values), direct)

    @staticmethod
    def score(a: BowDescription, b: BowDescription) -> float:
        """DBoW2's L1 score of two L1-normalised vectors: 1 - ||a - b||_1 / 2, in [0, 1]
        (1 for identical vectors, 0 when no word is shared). The sum |va| + |vb| - |va - vb| over the shared words
        is taken in ascending word id, one word after the other (DBoW2's L1Scoring walks its sorted map the same way),
        so a score is bit-for-bit the one the former dict loop gave."""
        wa, wb = a.word_weights, b.word_weights
        return 0.5 * l1_common_sum(wa.ids, wa.weights, wb.ids, wb.weights)
