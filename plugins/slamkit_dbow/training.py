"""Training a vocabulary: hierarchical k-means over binary descriptors, then TF-IDF weights (DBoW2's
``create``; Galvez-Lopez & Tardos, T-RO 2012, sec. III).

The root's descriptors are clustered into k groups (k-means++ seeds, bitwise-majority centres); each group
with more than one descriptor is clustered again, down to depth L. A group of at most k descriptors gives
one child per distinct descriptor (DBoW2's "trivial case"). Nodes are created level by level, the
children of a node consecutively; every node's k-means uses its own random stream seeded by
(seed, node id), so the result depends on the seed only, not on the number of threads. Each word gets
weight idf = ln(N / N_i), N training images, N_i of them containing the word.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slamkit.errors import ConfigError
from slamkit_dbow.kernels import kmeans, word_document_counts
from slamkit_dbow.vocabulary import Scoring, Vocabulary, Weighting

#: DBoW2 stops k-means when no assignment changes; this cap bounds the training time (it is rarely
#: reached below the first levels).
DEFAULT_MAX_ITERATIONS = 50


@dataclass(frozen=True)
class TrainingParams:
    """k: branching factor; L: depth; seed: random seed; max_iterations: cap on k-means centre updates per
    node; n_threads: threads that cluster sibling nodes (the result does not depend on it)."""

    k: int = 10
    L: int = 4
    seed: int = 0
    max_iterations: int = DEFAULT_MAX_ITERATIONS
    n_threads: int = 2

    def __post_init__(self) -> None:
        for key, value, low in (("k", self.k, 2), ("L", self.L, 1), ("max_iterations", self.max_iterations, 1)):
            if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < low:
                raise ConfigError(f"vocabulary training: {key} must be an integer >= {low}, got {value!r}")
        if self.k**self.L > 50_000_000:
            raise ConfigError(f"vocabulary training: k^L = {self.k}^{self.L} words is too many (max 5e7)")
        if isinstance(self.n_threads, bool) or not isinstance(self.n_threads, int) or self.n_threads < 1:
            raise ConfigError(f"vocabulary training: n_threads must be an integer >= 1, got {self.n_threads!r}")


def _cluster(desc64: NDArray[np.uint64], k: int, seed: int, node_id: int, max_iterations: int) -> tuple[Any, Any]:
    """Cluster one node's descriptors: (centres (m, W), assignment (n,)) with m <= k."""
    n = desc64.shape[0]
    if n <= k:  # DBoW2's trivial case: one child per (distinct) descriptor
        uniq, first, inverse = np.unique(desc64, axis=0, return_index=True, return_inverse=True)
        order = np.argsort(first)  # children in order of first occurrence
        rank = np.empty_like(order)
        rank[order] = np.arange(order.size)
        return np.ascontiguousarray(uniq[order]), rank[inverse.reshape(-1)].astype(np.int32)
    rng = np.random.default_rng([seed & 0xFFFFFFFF, node_id])
    first_row = int(rng.integers(n))
    uniforms = rng.random(k)
    centres, assign, _ = kmeans(desc64, k, first_row, uniforms, max_iterations)
    return centres, assign


def train_vocabulary(
    images: Sequence[NDArray[np.uint8]],
    params: TrainingParams = TrainingParams(),
    progress: Callable[[int], None] | None = None,
    metadata: dict[str, Any] | None = None,
) -> Vocabulary:
    """Train a vocabulary from the descriptors of training images.

    images: one (N_j, D) uint8 descriptor array per training image (D a multiple of 8; 32 for ORB). The
        images are the documents of TF-IDF.
    progress: called with the number of descriptors clustered after each node (total L * sum N_j, less
        when branches stop early), for a progress bar.
    """
    arrays = [np.ascontiguousarray(a, np.uint8) for a in images]
    if not arrays or sum(a.shape[0] for a in arrays) == 0:
        raise ConfigError("vocabulary training: no descriptors to train on (no images, or no features found)")
    widths = {a.shape[1] for a in arrays if a.ndim == 2 and a.shape[0]}
    if any(a.ndim != 2 for a in arrays) or len(widths) != 1 or next(iter(widths)) % 8:
        raise ConfigError(
            f"vocabulary training: descriptors must be (N, D) uint8 arrays with one D, a multiple of 8; got widths {sorted(widths)}"
        )
    all_desc = np.concatenate([a for a in arrays if a.shape[0]], axis=0)
    desc64 = all_desc.view(np.uint64)
    width = desc64.shape[1]

    parent: list[int] = [-1]
    centre_rows: list[NDArray[np.uint64]] = [np.zeros((1, width), np.uint64)]
    frontier: list[tuple[int, NDArray[np.int64]]] = [(0, np.arange(desc64.shape[0], dtype=np.int64))]
    with ThreadPoolExecutor(max_workers=params.n_threads) as pool:
        for depth in range(params.L):

            def work(item: tuple[int, NDArray[np.int64]]) -> tuple[Any, Any]:
                node, idx = item
                out = _cluster(np.ascontiguousarray(desc64[idx]), params.k, params.seed, node, params.max_iterations)
                if progress is not None:
                    progress(int(idx.size))
                return out

            results = list(pool.map(work, frontier))
            next_frontier: list[tuple[int, NDArray[np.int64]]] = []
            for (node, idx), (centres, assign) in zip(frontier, results, strict=True):
                first_child = len(parent)
                parent.extend([node] * centres.shape[0])
                centre_rows.append(centres)
                if depth + 1 < params.L:
                    order = np.argsort(assign, kind="stable")
                    counts = np.bincount(assign, minlength=centres.shape[0])
                    groups = np.split(idx[order], np.cumsum(counts)[:-1])
                    for c, g in enumerate(groups):
                        # DBoW2 recurses into groups of more than one descriptor; we also stop on groups of
                        # identical descriptors (they would only grow a chain of single children)
                        if g.size > 1 and np.any(desc64[g[1:]] != desc64[g[0]]):
                            next_frontier.append((first_child + c, g))
            frontier = next_frontier

    n_nodes = len(parent)
    parent_arr = np.asarray(parent, np.int32)
    descriptors = np.concatenate(centre_rows, axis=0).view(np.uint8).reshape(n_nodes, -1)
    has_child = np.zeros(n_nodes, bool)
    has_child[parent_arr[1:]] = True
    is_leaf = ~has_child
    # provisional vocabulary (weights 1) to find every training descriptor's word
    vocab = Vocabulary(params.k, params.L, parent_arr, descriptors, is_leaf.astype(np.float64), is_leaf)
    words = vocab.words_and_nodes(all_desc, 0).words
    starts = np.zeros(len(arrays) + 1, np.int64)
    np.cumsum([a.shape[0] for a in arrays], out=starts[1:])
    n_i = word_document_counts(words, starts, vocab.n_words)
    idf = np.zeros(vocab.n_words)
    seen = n_i > 0
    idf[seen] = np.log(len(arrays) / n_i[seen])
    weights = np.zeros(n_nodes)
    weights[vocab.word_nodes] = idf
    meta = dict(metadata or {})
    meta.update(
        {
            "k": params.k,
            "L": params.L,
            "seed": params.seed,
            "max_iterations": params.max_iterations,
            "n_images": len(arrays),
            "n_descriptors": int(all_desc.shape[0]),
        }
    )
    return Vocabulary(
        params.k, params.L, parent_arr, descriptors, weights, is_leaf, Scoring.L1_NORM, Weighting.TF_IDF, meta
    )
