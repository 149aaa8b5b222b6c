"""numba kernels of the vocabulary: descending the tree, and one k-means clustering of binary descriptors.

Descriptors are handled as (N, W) uint64 rows (a 32-byte ORB descriptor is W = 4 words) so a Hamming
distance is W xor + popcount. Every kernel is ``nogil``: the trainer clusters sibling nodes on several
threads and tracking can transform a frame while local mapping runs.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

U64 = NDArray[np.uint64]
I32 = NDArray[np.int32]
I64 = NDArray[np.int64]
F64 = NDArray[np.float64]


@numba.njit(cache=True, nogil=True, inline="always")
def _popcount64(x: np.uint64) -> int:  # pragma: no cover - numba
    """Number of set bits of a 64-bit word (SWAR)."""
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return int((x * np.uint64(0x0101010101010101)) >> np.uint64(56))


@numba.njit(cache=True, nogil=True, inline="always")
def _distance(a: U64, i: int, b: U64, j: int) -> int:  # pragma: no cover - numba
    """Hamming distance (bits) between row i of a and row j of b."""
    d = 0
    for w in range(a.shape[1]):
        d += _popcount64(a[i, w] ^ b[j, w])
    return d


@numba.njit(cache=True, nogil=True)
def descend(
    desc: U64, node_desc: U64, child_start: I64, children: I32, word_of_node: I32, level: int
) -> tuple[I32, I32]:  # pragma: no cover - numba
    """Propagate each descriptor from the root to a leaf, taking the closest child at every level.

    desc: (N, W) query descriptors; node_desc: (n_nodes, W); the children of node n are
    ``children[child_start[n]:child_start[n + 1]]`` (none for a leaf); word_of_node: (n_nodes,) word id of
    each leaf. Ties go to the first child, as DBoW2's ``transform``.
    Returns (N,) word ids and (N,) the node crossed at depth ``level`` (the root for level <= 0; the leaf
    itself when the leaf is shallower than ``level``).
    """
    n = desc.shape[0]
    words = np.empty(n, np.int32)
    nodes = np.empty(n, np.int32)
    for i in range(n):
        node = 0
        depth = 0
        at_level = 0
        while child_start[node + 1] > child_start[node]:
            best = -1
            best_d = 1 << 30
            for s in range(child_start[node], child_start[node + 1]):
                c = children[s]
                d = _distance(desc, i, node_desc, c)
                if d < best_d:
                    best_d = d
                    best = c
            node = best
            depth += 1
            if depth == level:
                at_level = node
        if depth < level:
            at_level = node
        words[i] = word_of_node[node]
        nodes[i] = at_level
    return words, nodes


@numba.njit(cache=True, nogil=True)
def _assign(desc: U64, centres: U64, n_centres: int, out: I32) -> None:  # pragma: no cover - numba
    """out[i] = index of the closest of the first n_centres centres (ties: the lowest index)."""
    for i in range(desc.shape[0]):
        best = 0
        best_d = _distance(desc, i, centres, 0)
        for c in range(1, n_centres):
            d = _distance(desc, i, centres, c)
            if d < best_d:
                best_d = d
                best = c
        out[i] = best


@numba.njit(cache=True, nogil=True)
def majority_centres(desc: U64, assign: I32, n_centres: int) -> U64:  # pragma: no cover - numba
    """Bitwise-majority centre of each cluster: a bit is set when at least half of the cluster's
    descriptors have it (ties set the bit, as DBoW2's FORB::meanValue). Empty clusters get all-zero centres.

    desc: (N, W); assign: (N,) cluster of each descriptor in [0, n_centres). Returns (n_centres, W).
    """
    n_words = desc.shape[1]
    counts = np.zeros((n_centres, n_words * 64), np.int32)
    sizes = np.zeros(n_centres, np.int64)
    for i in range(desc.shape[0]):
        c = assign[i]
        sizes[c] += 1
        for w in range(n_words):
            x = desc[i, w]
            base = w * 64
            for b in range(64):
                counts[c, base + b] += np.int32((x >> np.uint64(b)) & np.uint64(1))
    out = np.zeros((n_centres, n_words), np.uint64)
    for c in range(n_centres):
        for w in range(n_words):
            acc = np.uint64(0)
            for b in range(64):
                if 2 * counts[c, w * 64 + b] >= sizes[c] and sizes[c] > 0:
                    acc |= np.uint64(1) << np.uint64(b)
            out[c, w] = acc
    return out


@numba.njit(cache=True, nogil=True)
def kmeanspp_seeds(desc: U64, k: int, first: int, uniforms: F64) -> I64:  # pragma: no cover - numba
    """k-means++ seeding (Arthur & Vassilvitskii 2007): the first seed is row ``first``; each next one is
    drawn with probability proportional to D(x)^2, D = Hamming distance to the closest seed so far, using
    ``uniforms[j]`` in [0, 1) for draw j. Stops early when every descriptor equals a seed.

    Returns the (m,) row indices of the seeds, m <= k, all distinct descriptors.
    """
    n = desc.shape[0]
    seeds = np.empty(k, np.int64)
    seeds[0] = first
    m = 1
    d2 = np.empty(n, np.float64)
    for i in range(n):
        d = _distance(desc, i, desc, first)
        d2[i] = d * d
    while m < k:
        total = 0.0
        for i in range(n):
            total += d2[i]
        if total <= 0.0:
            break
        cut = uniforms[m] * total
        acc = 0.0
        pick = -1
        for i in range(n):
            if d2[i] > 0.0:
                acc += d2[i]
                pick = i
                if acc > cut:
                    break
        seeds[m] = pick
        m += 1
        for i in range(n):
            if d2[i] > 0.0:
                d = _distance(desc, i, desc, pick)
                if d * d < d2[i]:
                    d2[i] = d * d
    return seeds[:m].copy()


@numba.njit(cache=True, nogil=True)
def kmeans(
    desc: U64, k: int, first: int, uniforms: F64, max_iterations: int
) -> tuple[U64, I32, int]:  # pragma: no cover - numba
    """Binary k-means of one node: k-means++ seeds, then alternate bitwise-majority centres and
    nearest-centre assignment until no assignment changes (DBoW2's stopping rule) or ``max_iterations``
    centre updates were made. The returned assignment is always the one against the returned centres.
    Clusters left empty are dropped (their centres would be words no training descriptor reaches).

    desc: (N, W) with N > k. Returns centres (m, W), assign (N,) in [0, m), iterations done.
    """
    seeds = kmeanspp_seeds(desc, k, first, uniforms)
    m = seeds.shape[0]
    centres = np.empty((m, desc.shape[1]), np.uint64)
    for c in range(m):
        centres[c] = desc[seeds[c]]
    assign = np.empty(desc.shape[0], np.int32)
    _assign(desc, centres, m, assign)
    new_assign = np.empty_like(assign)
    iterations = 0
    for _ in range(max_iterations):
        centres = majority_centres(desc, assign, m)
        _assign(desc, centres, m, new_assign)
        iterations += 1
        changed = False
        for i in range(desc.shape[0]):
            if new_assign[i] != assign[i]:
                changed = True
                break
        assign[:] = new_assign
        if not changed:
            break
    # compact: drop empty clusters, keep the order of the others
    sizes = np.zeros(m, np.int64)
    for i in range(desc.shape[0]):
        sizes[assign[i]] += 1
    remap = np.full(m, -1, np.int32)
    kept = 0
    for c in range(m):
        if sizes[c] > 0:
            remap[c] = kept
            kept += 1
    out = np.empty((kept, desc.shape[1]), np.uint64)
    for c in range(m):
        if remap[c] >= 0:
            out[remap[c]] = centres[c]
    for i in range(desc.shape[0]):
        assign[i] = remap[assign[i]]
    return out, assign, iterations


@numba.njit(cache=True, nogil=True)
def word_document_counts(words: I32, image_start: I64, n_words: int) -> I64:  # pragma: no cover - numba
    """Ni of TF-IDF: for each word, the number of images (documents) in which it occurs at least once.

    words: (N,) word of every training descriptor, images concatenated; image j owns
    ``words[image_start[j]:image_start[j + 1]]``.
    """
    counts = np.zeros(n_words, np.int64)
    last_seen = np.full(n_words, -1, np.int64)
    for j in range(image_start.shape[0] - 1):
        for s in range(image_start[j], image_start[j + 1]):
            w = words[s]
            if last_seen[w] != j:
                last_seen[w] = j
                counts[w] += 1
    return counts


@numba.njit(cache=True, nogil=True)
def tokens_per_line(text: NDArray[np.uint8]) -> I32:  # pragma: no cover - numba
    """Number of whitespace-separated tokens on each line of an ASCII text (lines end with '\\n'; a last
    line without one counts too). Blanks are space, tab, CR and LF."""
    n_lines = 1
    for i in range(text.shape[0]):
        if text[i] == 10:
            n_lines += 1
    counts = np.zeros(n_lines, np.int32)
    line = 0
    prev_blank = True
    for i in range(text.shape[0]):
        c = text[i]
        blank = c == 32 or c == 9 or c == 13 or c == 10
        if not blank and prev_blank:
            counts[line] += 1
        if c == 10:
            line += 1
        prev_blank = blank
    return counts


@numba.njit(cache=True, nogil=True)
def l1_common_sum(ids_a: I32, w_a: F64, ids_b: I32, w_b: F64) -> float:  # pragma: no cover - numba
    """Sum over the words two bags share of |va| + |vb| - |va - vb| (DBoW2's L1Scoring before its factor 1/2).

    ids_a / ids_b: (Ka,) / (Kb,) strictly ascending word ids; w_a / w_b: their weights. The two sorted lists are
    merged and the terms added one at a time in ascending word id (no pairwise summation), so the float result is
    the same whichever bag is the smaller and the same as a Python loop over the shared words in that order.
    """
    s = 0.0
    i = 0
    j = 0
    na = ids_a.shape[0]
    nb = ids_b.shape[0]
    while i < na and j < nb:
        a = ids_a[i]
        b = ids_b[j]
        if a < b:
            i += 1
        elif a > b:
            j += 1
        else:
            va = w_a[i]
            vb = w_b[j]
            s += abs(va) + abs(vb) - abs(va - vb)
            i += 1
            j += 1
    return s
