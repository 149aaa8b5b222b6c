"""BoW-guided matching (ORB-SLAM's ORBmatcher::SearchByBoW, sec. III-E / V-A / VI-B): brute-force
matching restricted to the features of two images that fall in the same vocabulary node of the direct
index, with the nearest/second-nearest ratio test, a maximum distance, each feature matched once, and
the rotation-consistency histogram. Used for relocalization, loop detection and (with masks selecting the
features without a map point) to find pairs to triangulate."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from slamkit.features import Features
from slamkit.interfaces import BowDescription
from slamkit.pipeline.matching import hamming_matrix, resolve_one_to_one, rotation_consistent
from slamkit_dbow.vocabulary import VocabularyError

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
    d1, d2 = feats1.descriptors, feats2.descriptors
    q_all: list[I64] = []
    t_all: list[I64] = []
    dist_all: list[NDArray[np.int32]] = []
    for node, idx1 in bow1.direct_index.items():
        idx2 = bow2.direct_index.get(node)
        if idx2 is None:
            continue
        if m1 is not None:
            idx1 = idx1[m1[idx1]]
        if m2 is not None:
            idx2 = idx2[m2[idx2]]
        if idx1.size == 0 or idx2.size == 0:
            continue
        dist = hamming_matrix(d1[idx1], d2[idx2])
        best_j = np.argmin(dist, axis=1)
        best = dist[np.arange(idx1.size), best_j]
        # second-nearest distance; a lone candidate has none (inf: it passes the ratio test)
        second = np.full(idx1.size, np.inf)
        if idx2.size > 1:
            second = np.partition(dist, 1, axis=1)[:, 1].astype(np.float64)
        ok = (best <= max_distance) & (best < ratio * second)
        q_all.append(idx1[ok])
        t_all.append(idx2[best_j[ok]])
        dist_all.append(best[ok])
    if not q_all:
        return np.zeros((0, 2), np.int64)
    q = np.concatenate(q_all).astype(np.int64)
    t = np.concatenate(t_all).astype(np.int64)
    dist = np.concatenate(dist_all)
    keep = resolve_one_to_one(q, t, dist)
    q, t = q[keep], t[keep]
    if rotation_bins and q.size:
        diff = feats1.angle_deg[q].astype(np.float64) - feats2.angle_deg[t].astype(np.float64)
        ok = rotation_consistent(diff, rotation_bins)
        q, t = q[ok], t[ok]
    order = np.argsort(q, kind="stable")
    return np.stack([q[order], t[order]], axis=1)
