"""BoW-guided matching through the direct index: two walks of the vocabulary nodes two images share, as
ORB-SLAM's ORBmatcher has them.

- ``match_by_bow`` (SearchByBoW, sec. III-E / V-A / VI-B): brute-force matching restricted to the features of
  the same node, with the nearest/second-nearest ratio test, a maximum distance, each feature matched once, and
  the rotation-consistency histogram. Used for tracking the reference keyframe, relocalization and loop
  detection.
- ``node_pairs`` (SearchForTriangulation's FeatureVector walk, sec. VI-C): every close pair of allowed features of
  the same node, the candidates local mapping filters with the epipolar constraint before triangulating.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

from slamkit.features import Features
from slamkit.interfaces import BowDescription
from slamkit.pipeline.matching import resolve_one_to_one, rotation_consistent, row_distance
from slamkit_dbow.vocabulary import VocabularyError

I32 = NDArray[np.int32]
I64 = NDArray[np.int64]


def _mask(mask: NDArray[np.bool_] | None, n: int, name: str) -> NDArray[np.bool_] | None:
    if mask is None:
        return None
    m = np.asarray(mask, bool)
    if m.shape != (n,):
        raise VocabularyError(f"{name} must be a ({n},) bool array (one entry per feature), got shape {m.shape}")
    return m


def match_by_bow(
    feats1: Features,
    bow1: BowDescription,
    feats2: Features,
    bow2: BowDescription,
    ratio: float,
    max_distance: int,
    rotation_bins: int | None,
    mask1: NDArray[np.bool_] | None = None,
    mask2: NDArray[np.bool_] | None = None,
) -> I64:
    """Match the features of two images through their direct indexes (same node at the direct-index level).

    For each eligible feature i of image 1, the best and second-best features of image 2 in the same node
    are found; the match (i, best) is kept when best <= ``max_distance`` bits (ORB-SLAM: TH_LOW = 50) and
    best < ``ratio`` * second (a lone candidate has no second and passes). Each feature of image 2 then keeps
    only its closest claim; with ``rotation_bins`` (ORB-SLAM: 30, HISTO_LENGTH; None: no check) only matches
    whose orientation difference angle1 - angle2 falls in the three main histogram bins survive.
    mask1 / mask2: (N1,) / (N2,) bool, the features allowed to match (None: all).
    The thresholds are the caller's (slamkit's pipeline passes ``pipeline.matcher``: ratio 0.7 with the
    reference keyframe, 0.75 for relocalization and loop detection).

    Returns (K, 2) int64 index pairs (feature of image 1, feature of image 2), sorted by the first index.
    """
    n1, n2 = len(feats1), len(feats2)
    m1, m2 = _mask(mask1, n1, "mask1"), _mask(mask2, n2, "mask2")
    d1 = np.ascontiguousarray(feats1.descriptors, np.uint8)
    d2 = np.ascontiguousarray(feats2.descriptors, np.uint8)
    if d1.shape[1] % 8 or d1.shape[1] != d2.shape[1]:
        raise VocabularyError(f"descriptors must be (N, D) uint8 with one D, a multiple of 8: {d1.shape}, {d2.shape}")
    x, y = bow1.direct, bow2.direct
    q, t, dist = _nearest_in_shared_nodes(
        x.nodes,
        x.offsets,
        x.features,
        y.nodes,
        y.offsets,
        y.features,
        np.ones(n1, bool) if m1 is None else m1,
        np.ones(n2, bool) if m2 is None else m2,
        d1.view(np.uint64),
        d2.view(np.uint64),
        int(max_distance),
        float(ratio),
    )
    if q.size == 0:
        return np.zeros((0, 2), np.int64)
    keep = resolve_one_to_one(q, t, dist)
    q, t = q[keep], t[keep]
    if rotation_bins and q.size:
        diff = feats1.angle_deg[q].astype(np.float64) - feats2.angle_deg[t].astype(np.float64)
        ok = rotation_consistent(diff, rotation_bins)
        q, t = q[ok], t[ok]
    order = np.argsort(q, kind="stable")
    return np.stack([q[order], t[order]], axis=1)


@numba.njit(cache=True, nogil=True)
def _shared_nodes(nodes1: I32, nodes2: I32) -> tuple[I64, I64]:  # pragma: no cover - compiled
    """Positions (i, j) with ``nodes1[i] == nodes2[j]`` of two ascending node-id lists, in ascending node order: the
    merge both per-node searches walk."""
    shared1 = np.empty(min(nodes1.shape[0], nodes2.shape[0]), np.int64)
    shared2 = np.empty_like(shared1)
    n = i = j = 0
    while i < nodes1.shape[0] and j < nodes2.shape[0]:
        if nodes1[i] < nodes2[j]:
            i += 1
        elif nodes1[i] > nodes2[j]:
            j += 1
        else:
            shared1[n] = i
            shared2[n] = j
            n += 1
            i += 1
            j += 1
    return shared1[:n], shared2[:n]


@numba.njit(cache=True, nogil=True)
def _nearest_in_shared_nodes(
    nodes1: I32,
    ptr1: I64,
    feats1: I32,
    nodes2: I32,
    ptr2: I64,
    feats2: I32,
    mask1: NDArray[np.bool_],
    mask2: NDArray[np.bool_],
    desc1: NDArray[np.uint64],
    desc2: NDArray[np.uint64],
    max_distance: int,
    ratio: float,
) -> tuple[I64, I64, I64]:  # pragma: no cover - compiled
    """SearchByBoW's per-node search: merge the two sorted node lists; for every shared node and every allowed feature
    a of image 1 in it, the nearest allowed feature b of image 2 in the node (the first of equal ones) and the second
    smallest distance (equal to the nearest when two are as close; none for a lone candidate). Keeps (a, b, distance)
    when distance <= max_distance and distance < ratio * second (a lone candidate passes), in node order then a's
    direct-index order: the numpy version's argmin / partition per node, in one compiled pass (GIL released)."""
    shared1, shared2 = _shared_nodes(nodes1, nodes2)
    n_out = 0
    for k in range(shared1.shape[0]):
        n_out += ptr1[shared1[k] + 1] - ptr1[shared1[k]]
    q = np.empty(n_out, np.int64)
    t = np.empty(n_out, np.int64)
    d = np.empty(n_out, np.int64)
    n = 0
    for k in range(shared1.shape[0]):
        i, j = shared1[k], shared2[k]
        for s in range(ptr1[i], ptr1[i + 1]):
            a = feats1[s]
            if not mask1[a]:
                continue
            best = -1
            best_b = -1
            second = np.inf
            for u in range(ptr2[j], ptr2[j + 1]):
                b = feats2[u]
                if not mask2[b]:
                    continue
                dist = row_distance(desc1, a, desc2, b)
                if best < 0 or dist < best:
                    if best >= 0:
                        second = float(best)
                    best = dist
                    best_b = b
                elif dist < second:
                    second = float(dist)
            if best >= 0 and best <= max_distance and best < ratio * second:
                q[n] = a
                t[n] = best_b
                d[n] = best
                n += 1
    return q[:n], t[:n], d[:n]


@numba.njit(cache=True, nogil=True)
def _node_pair_matches(
    nodes1: I32,
    ptr1: I64,
    feats1: I32,
    nodes2: I32,
    ptr2: I64,
    feats2: I32,
    mask1: NDArray[np.bool_],
    mask2: NDArray[np.bool_],
    desc1: NDArray[np.uint64],
    desc2: NDArray[np.uint64],
    max_distance: int,
) -> tuple[I64, I64, I64]:  # pragma: no cover - compiled
    """Merge the two sorted node lists (direct indexes as CSR arrays: ``DirectIndex``); for every shared node, every (allowed feature of 1, allowed feature of 2)
    pair within max_distance bits -> (a, b, distance), in node order, then a's, then b's (direct-index order)."""
    shared1, shared2 = _shared_nodes(nodes1, nodes2)
    n_pairs = 0
    for k in range(shared1.shape[0]):
        i, j = shared1[k], shared2[k]
        n_pairs += (ptr1[i + 1] - ptr1[i]) * (ptr2[j + 1] - ptr2[j])
    a = np.empty(n_pairs, np.int64)
    b = np.empty(n_pairs, np.int64)
    d = np.empty(n_pairs, np.int64)
    n = 0
    for k in range(shared1.shape[0]):
        i, j = shared1[k], shared2[k]
        for s in range(ptr1[i], ptr1[i + 1]):
            x = feats1[s]
            if not mask1[x]:
                continue
            for t in range(ptr2[j], ptr2[j + 1]):
                y = feats2[t]
                if not mask2[y]:
                    continue
                dist = row_distance(desc1, x, desc2, y)
                if dist <= max_distance:
                    a[n] = x
                    b[n] = y
                    d[n] = dist
                    n += 1
    return a[:n], b[:n], d[:n]


def node_pairs(
    feats1: Features,
    bow1: BowDescription,
    feats2: Features,
    bow2: BowDescription,
    mask1: NDArray[np.bool_] | None,
    mask2: NDArray[np.bool_] | None,
    max_distance: int,
) -> tuple[I64, I64, I64]:
    """The candidates of ORB-SLAM's SearchForTriangulation, which walks the two images' FeatureVectors: every pair
    (feature a of image 1, feature b of image 2) under the same direct-index node, both allowed by the masks
    (mask1 (N1,) / mask2 (N2,) bool, None: all; local mapping passes the features without a map point), with Hamming
    distance <= ``max_distance`` bits (pipeline.matcher.th_low) -> (a, b, distance) (K,) int64 arrays, in node
    order, then a, then b (one compiled pass, GIL released)."""
    m1 = _mask(mask1, len(feats1), "mask1")
    m2 = _mask(mask2, len(feats2), "mask2")
    m1 = np.ones(len(feats1), bool) if m1 is None else m1
    m2 = np.ones(len(feats2), bool) if m2 is None else m2
    d1 = np.ascontiguousarray(feats1.descriptors, np.uint8)
    d2 = np.ascontiguousarray(feats2.descriptors, np.uint8)
    if d1.shape[1] % 8 or d1.shape[1] != d2.shape[1]:
        raise VocabularyError(f"descriptors must be (N, D) uint8 with one D, a multiple of 8: {d1.shape}, {d2.shape}")
    x, y = bow1.direct, bow2.direct
    return _node_pair_matches(
        x.nodes,
        x.offsets,
        x.features,
        y.nodes,
        y.offsets,
        y.features,
        m1,
        m2,
        d1.view(np.uint64),
        d2.view(np.uint64),
        int(max_distance),
    )
