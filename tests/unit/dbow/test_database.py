"""Keyframe database (inverted index) and ORB-SLAM's covisibility grouping of candidates."""

from __future__ import annotations

from collections.abc import Sequence

import pytest
from slamkit_dbow.covisibility import group_by_covisibility
from slamkit_dbow.database import KeyframeDatabase
from slamkit_dbow.vocabulary import Vocabulary

from slamkit.errors import ConfigError
from slamkit.interfaces import BowDescription


def _bow(words: dict[int, float]) -> BowDescription:
    total = sum(words.values())
    return BowDescription({w: v / total for w, v in words.items()}, {})


def _db() -> KeyframeDatabase:
    db = KeyframeDatabase(Vocabulary.score)
    db.add(1, _bow({1: 1, 2: 1, 3: 1}))
    db.add(2, _bow({3: 1, 4: 1}))
    db.add(3, _bow({7: 1}))
    return db


def test_inverted_index_follows_insertion_and_removal() -> None:
    db = _db()
    assert db.keyframes_with_word(3) == [1, 2] and db.keyframes_with_word(7) == [3]
    db.remove(2)
    assert db.keyframes_with_word(3) == [1] and db.keyframes_with_word(4) == []
    assert 2 not in db and len(db) == 2
    db.remove(2)  # culling an unknown keyframe is a no-op (ORB-SLAM's erase)
    db.add(1, _bow({9: 1}))  # re-adding replaces the old words
    assert db.keyframes_with_word(1) == [] and db.keyframes_with_word(9) == [1]


def test_query_scores_only_keyframes_sharing_words_best_first() -> None:
    db = _db()
    q = _bow({3: 1, 4: 1, 5: 1})
    result = db.query(q)
    assert [kf for kf, _ in result] == [2, 1]  # keyframe 3 shares no word
    assert result[0][1] == pytest.approx(2 / 3) and result[1][1] == pytest.approx(1 / 3)
    assert db.query(q, exclude=[2]) == [(1, pytest.approx(1 / 3))]
    assert db.query(_bow({4: 1, 5: 1})) == [(2, pytest.approx(0.5))]
    assert db.query(_bow({100: 1})) == []
    # keyframe 2 shares 2 words, keyframe 1 one: with ORB-SLAM's 0.8 only keyframe 2 is scored
    assert [kf for kf, _ in db.query(q, min_common_ratio=0.8)] == [2]
    assert db.common_words(q) == {1: 1, 2: 2}


def test_identical_bow_scores_one() -> None:
    db = _db()
    assert db.query(_bow({1: 1, 2: 1, 3: 1}))[0] == (1, pytest.approx(1.0))


def _neighbors(graph: dict[int, list[int]]):  # type: ignore[no-untyped-def]
    calls: list[tuple[int, int]] = []

    def fn(kf: int, n: int) -> Sequence[int]:
        calls.append((kf, n))
        return graph.get(kf, [])[:n]

    fn.calls = calls  # type: ignore[attr-defined]
    return fn


def test_grouping_accumulates_covisible_scores_and_keeps_75_percent() -> None:
    # place A: keyframes 10, 11, 12 covisible; place B: 20, 21; lone 30
    graph = {10: [11, 12], 11: [10, 12], 12: [11, 10], 20: [21], 21: [20], 30: []}
    scored = [(10, 0.30), (11, 0.35), (12, 0.25), (20, 0.40), (21, 0.30), (30, 0.5)]
    fn = _neighbors(graph)
    groups = group_by_covisibility(scored, fn)
    # group scores: A = 0.9 (rep 11), B = 0.7 (rep 20), lone 30 = 0.5; 0.75 * 0.9 = 0.675 keeps A and B
    assert [kf for kf, _ in groups] == [11, 20]
    assert groups[0][1] == pytest.approx(0.9) and groups[1][1] == pytest.approx(0.7)
    assert all(n == 10 for _, n in fn.calls)  # ORB-SLAM: the 10 best covisible keyframes


def test_grouping_min_score_and_unscored_neighbours() -> None:
    graph = {1: [2, 3], 2: [1], 3: [1]}
    # 3 was not scored (shared too few words): it adds nothing. 2 scores below min_score: not a candidate,
    # but it still adds to 1's group (ORB-SLAM adds every scored neighbour's score).
    groups = group_by_covisibility([(1, 0.5), (2, 0.2)], _neighbors(graph), min_score=0.3)
    assert groups == [(1, pytest.approx(0.7))]
    assert group_by_covisibility([(1, 0.1)], _neighbors(graph), min_score=0.3) == []
    assert group_by_covisibility([], _neighbors(graph)) == []


def test_grouping_reports_each_representative_once() -> None:
    graph = {1: [2], 2: [1]}
    assert group_by_covisibility([(1, 0.4), (2, 0.6)], _neighbors(graph)) == [(2, pytest.approx(1.0))]


def test_grouping_rejects_bad_ratio() -> None:
    with pytest.raises(ConfigError, match="group_min_ratio"):
        group_by_covisibility([], _neighbors({}), min_ratio=1.5)


def test_loop_and_relocalization_candidates() -> None:
    db = KeyframeDatabase(Vocabulary.score)
    db.add(0, _bow({1: 1, 2: 1, 3: 1, 4: 1}))  # the current keyframe's covisible neighbour
    db.add(5, _bow({1: 1, 2: 1, 3: 1, 9: 1}))  # the loop place
    db.add(6, _bow({1: 1, 2: 1, 3: 1, 8: 1}))  # covisible with 5
    db.add(7, _bow({1: 1, 10: 1, 11: 1, 12: 1}))  # weak
    graph = {5: [6], 6: [5], 0: [], 7: []}
    q = _bow({1: 1, 2: 1, 3: 1, 4: 1})
    loops = db.loop_candidates(q, connected={0}, min_score=0.5, neighbors=_neighbors(graph))
    # 5 and 6 tie at 0.75, so each candidate's group {5, 6} (1.5) is represented by itself (ORB-SLAM
    # replaces the representative only by a strictly better member); 7 shares too few words
    assert loops == [(5, pytest.approx(1.5)), (6, pytest.approx(1.5))]
    reloc = db.relocalization_candidates(q, _neighbors(graph))
    # every keyframe is eligible: 0 shares all 4 words, 5 and 6 only 3 (not > 0.8 * 4): 0 alone is scored
    assert reloc == [(0, pytest.approx(1.0))]
    db.remove(0)  # culled: now 5 and 6 share the most words and form the group
    reloc = db.relocalization_candidates(q, _neighbors(graph))
    assert reloc == [(5, pytest.approx(1.5)), (6, pytest.approx(1.5))]
    db.remove(6)
    assert db.relocalization_candidates(q, _neighbors(graph)) == [(5, pytest.approx(0.75))]
