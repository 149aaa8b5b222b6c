"""The keyframe database of ORB-SLAM (sec. III-E, KeyFrameDatabase): an inverted index from each visual
word to the keyframes whose bag of words contains it, and the candidate searches built on it.

Queries only score keyframes that share a word with the query (the inverted index makes that cheap).
``loop_candidates`` and ``relocalization_candidates`` follow ORB-SLAM's DetectLoopCandidates and
DetectRelocalizationCandidates: keep the keyframes sharing more than ``min_common_ratio`` (0.8) of the
largest number of common words, score them, then group each with its covisible neighbours and keep the
groups whose accumulated score exceeds ``group_min_ratio`` (0.75) of the best group's (covisibility.py).
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Sequence

from slamkit.errors import ConfigError
from slamkit.interfaces import BowDescription
from slamkit_dbow.covisibility import NeighborsFn, group_by_covisibility

ScoreFn = Callable[[BowDescription, BowDescription], float]


def _ratio(value: float, key: str) -> float:
    v = float(value)
    if not 0.0 <= v <= 1.0:
        raise ConfigError(f"place.{key} must be in [0, 1], got {value!r}")
    return v


class KeyframeDatabase:
    """Inverted index word -> keyframes, with every keyframe's bag of words.

    score: similarity of two bags of words (the vocabulary's L1 score).
    Iteration orders are insertion orders, so results are deterministic (ties: lower keyframe id first).
    """

    def __init__(self, score: ScoreFn) -> None:
        self._score = score
        # word -> keyframe ids in insertion order (ORB-SLAM's vector<list<KeyFrame*>> mvInvertedFile): a list of the
        # keyframes' shared int objects costs 8 bytes an entry, where a dict as an ordered set cost ~40
        self._inverted: dict[int, list[int]] = {}
        self._bows: dict[int, BowDescription] = {}

    def __len__(self) -> int:
        return len(self._bows)

    def __contains__(self, keyframe_id: object) -> bool:
        return keyframe_id in self._bows

    def keyframe_ids(self) -> list[int]:
        return list(self._bows)

    def bow(self, keyframe_id: int) -> BowDescription:
        """The bag of words stored for a keyframe (KeyError if it is not in the database)."""
        return self._bows[keyframe_id]

    def keyframes_with_word(self, word: int) -> list[int]:
        """The inverted-index entry of ``word``: keyframes whose bag of words contains it."""
        return list(self._inverted.get(word, ()))

    def add(self, keyframe_id: int, bow: BowDescription) -> None:
        """Insert a keyframe (replacing its previous bag of words if it was already there)."""
        kf = int(keyframe_id)
        if kf in self._bows:
            self.remove(kf)
        self._bows[kf] = bow
        inverted = self._inverted
        for word in bow.words:
            entry = inverted.get(word)
            if entry is None:
                inverted[word] = [kf]
            else:
                entry.append(kf)

    def remove(self, keyframe_id: int) -> None:
        """Erase a keyframe from the inverted index (keyframe culling). Unknown ids are ignored, as ORB-SLAM's
        KeyFrameDatabase::erase."""
        kf = int(keyframe_id)
        bow = self._bows.pop(kf, None)
        if bow is None:
            return
        for word in bow.words:
            entry = self._inverted.get(word)
            if entry is not None and kf in entry:
                entry.remove(kf)
                if not entry:
                    del self._inverted[word]

    def clear(self) -> None:
        self._inverted.clear()
        self._bows.clear()

    def common_words(self, bow: BowDescription, exclude: Collection[int] = ()) -> dict[int, int]:
        """Keyframe id -> number of words it shares with ``bow``, for every keyframe sharing at least one
        (and not in ``exclude``)."""
        excluded = set(exclude)
        counts: dict[int, int] = {}
        for word in bow.words:
            for kf in self._inverted.get(word, ()):
                if kf not in excluded:
                    counts[kf] = counts.get(kf, 0) + 1
        return counts

    def query(
        self, bow: BowDescription, exclude: Sequence[int] = (), min_common_ratio: float = 0.0
    ) -> list[tuple[int, float]]:
        """Keyframes sharing at least one word with ``bow`` (not in ``exclude``) with their scores, best
        first (ties: lower id first). With ``min_common_ratio`` > 0, only keyframes sharing more than that
        fraction of the largest number of common words are scored (ORB-SLAM: 0.8)."""
        counts = self.common_words(bow, exclude)
        if not counts:
            return []
        threshold = _ratio(min_common_ratio, "min_common_ratio") * max(counts.values())
        scored = [(kf, self._score(bow, self._bows[kf])) for kf, c in counts.items() if c > threshold]
        scored.sort(key=lambda ks: (-ks[1], ks[0]))
        return scored

    def loop_candidates(
        self,
        bow: BowDescription,
        connected: Collection[int],
        min_score: float,
        neighbors: NeighborsFn,
        min_common_ratio: float = 0.8,
        group_min_ratio: float = 0.75,
        n_covisible: int = 10,
    ) -> list[tuple[int, float]]:
        """ORB-SLAM's DetectLoopCandidates for the current keyframe's ``bow``.

        connected: the current keyframe and its covisible keyframes (never candidates). min_score: the
        lowest score between the current keyframe and its covisible neighbours (III-E / VI-A); keyframes
        scoring less are not candidates (they still add to their neighbours' group scores when they
        share enough words). neighbors(kf, n): a keyframe's n best covisible keyframes.
        Returns [(best keyframe of a group, the group's accumulated score)], best first.
        """
        scored = self.query(bow, exclude=list(connected), min_common_ratio=min_common_ratio)
        return group_by_covisibility(scored, neighbors, group_min_ratio, min_score, n_covisible)

    def relocalization_candidates(
        self,
        bow: BowDescription,
        neighbors: NeighborsFn,
        min_common_ratio: float = 0.8,
        group_min_ratio: float = 0.75,
        n_covisible: int = 10,
    ) -> list[tuple[int, float]]:
        """ORB-SLAM's DetectRelocalizationCandidates for a lost frame's ``bow``: as loop_candidates, with
        every keyframe eligible and no minimum score."""
        scored = self.query(bow, min_common_ratio=min_common_ratio)
        return group_by_covisibility(scored, neighbors, group_min_ratio, 0.0, n_covisible)
