"""Grouping place-recognition candidates by covisibility (ORB-SLAM sec. III-E, KeyFrameDatabase).

A single keyframe that looks like the query is weak evidence; a cluster of covisible keyframes that all
look like it is strong. Each candidate's score is accumulated with the scores of its best covisible
keyframes that were scored too, the group is represented by its best-scoring member, and every group
scoring above ``min_ratio`` (0.75) of the best group is kept.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from slamkit.errors import ConfigError

#: neighbors(keyframe_id, n) -> that keyframe's n best covisible keyframes, best first
#: (e.g. ``store.covisibility.best_neighbors``).
NeighborsFn = Callable[[int, int], Sequence[int]]


def group_by_covisibility(
    scored: Sequence[tuple[int, float]],
    neighbors: NeighborsFn,
    min_ratio: float = 0.75,
    min_score: float = 0.0,
    n_covisible: int = 10,
) -> list[tuple[int, float]]:
    """Covisibility groups of candidates, as ORB-SLAM's DetectLoopCandidates / DetectRelocalizationCandidates.

    scored: (keyframe id, score) of every keyframe that was scored against the query (those sharing enough
        words). Keyframes scoring at least ``min_score`` are candidates; all scored keyframes count as
        neighbours.
    neighbors: a keyframe's ``n_covisible`` best covisible keyframes (ORB-SLAM: 10).
    For each candidate, its group score is its score plus the scores of its scored neighbours, and the
    group's representative is its best-scoring member (the candidate itself on ties). Groups whose score
    exceeds ``min_ratio`` times the best group score (at least ``min_score``) are returned as
    (representative, group score), best first, each representative once (with its best group score).
    """
    if not 0.0 <= min_ratio <= 1.0:
        raise ConfigError(f"place.group_min_ratio must be in [0, 1], got {min_ratio!r}")
    if n_covisible < 0:
        raise ConfigError(f"place.n_covisible must be >= 0, got {n_covisible!r}")
    score_of = dict(scored)
    groups: list[tuple[int, float]] = []
    best_acc = min_score
    for kf, score in scored:
        if score < min_score:
            continue
        acc, best_kf, best = score, kf, score
        for nb in neighbors(kf, n_covisible):
            s = score_of.get(nb)
            if s is None or nb == kf:
                continue
            acc += s
            if s > best:
                best_kf, best = nb, s
        groups.append((best_kf, acc))
        best_acc = max(best_acc, acc)
    keep = min_ratio * best_acc
    out: dict[int, float] = {}
    for kf, acc in groups:
        if acc > keep and acc > out.get(kf, float("-inf")):
            out[kf] = acc
    return sorted(out.items(), key=lambda ka: (-ka[1], ka[0]))
