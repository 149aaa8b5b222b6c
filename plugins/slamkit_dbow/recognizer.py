"""``place=dbow``: a DBoW2 vocabulary plus ORB-SLAM's keyframe database behind slamkit's PlaceRecognizer."""

from __future__ import annotations

import threading
from collections.abc import Collection, Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from slamkit.errors import ConfigError
from slamkit.features import Features
from slamkit.interfaces import BowDescription
from slamkit_dbow.builtin import load_builtin_vocabulary
from slamkit_dbow.covisibility import NeighborsFn
from slamkit_dbow.database import KeyframeDatabase
from slamkit_dbow.files import load_vocabulary
from slamkit_dbow.matching import match_by_bow, node_pairs
from slamkit_dbow.vocabulary import Vocabulary

_cache_lock = threading.Lock()
_loaded: dict[str, Vocabulary] = {}


def get_vocabulary(spec: str | Path) -> Vocabulary:
    """The vocabulary named by ``spec``: "builtin" or a file path. Loaded once per process (read-only)."""
    key = str(spec) if str(spec) == "builtin" else str(Path(spec).expanduser().resolve())
    with _cache_lock:
        vocab = _loaded.get(key)
        if vocab is None:
            vocab = load_builtin_vocabulary() if key == "builtin" else load_vocabulary(key)
            _loaded[key] = vocab
        return vocab


def _int_param(value: object, key: str, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < low:
        raise ConfigError(f"place.{key} must be an integer >= {low}, got {value!r}")
    return int(value)


def _ratio_param(value: object, key: str) -> float:
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ConfigError(f"place.{key} must be a number in [0, 1], got {value!r}") from None
    if not 0.0 <= v <= 1.0:
        raise ConfigError(f"place.{key} must be a number in [0, 1], got {value!r}")
    return v


class DbowPlaceRecognizer:
    """Bag of binary words (DBoW2) place recognition with ORB-SLAM's keyframe database (sec. III-E).

    vocabulary: "builtin" (slamkit's own, trained on its synthetic world; see builtin.py) or the path of
        a vocabulary file: DBoW2 text (ORBvoc.txt, .txt.gz) or slamkit binary (.skvoc).
    direct_index_level: depth below the root of the direct-index nodes (ORB-SLAM: L = 6 with 4 levels up,
        i.e. depth 2; deeper = fewer candidates per node in BoW matching).
    min_common_ratio, group_min_ratio, n_covisible: ORB-SLAM's 0.8, 0.75 and 10 (KeyFrameDatabase).
    """

    def __init__(
        self,
        vocabulary: str = "builtin",
        direct_index_level: int = 2,
        min_common_ratio: float = 0.8,
        group_min_ratio: float = 0.75,
        n_covisible: int = 10,
        vocabulary_object: Vocabulary | None = None,
    ) -> None:
        self.vocabulary = vocabulary_object if vocabulary_object is not None else get_vocabulary(vocabulary)
        self.vocabulary_name = str(vocabulary) if vocabulary_object is None else "object"
        self.direct_index_level = _int_param(direct_index_level, "direct_index_level", 0)
        if self.direct_index_level > self.vocabulary.L:
            raise ConfigError(
                f"place.direct_index_level={direct_index_level} is deeper than the vocabulary (L={self.vocabulary.L})"
            )
        self.min_common_ratio = _ratio_param(min_common_ratio, "min_common_ratio")
        self.group_min_ratio = _ratio_param(group_min_ratio, "group_min_ratio")
        self.n_covisible = _int_param(n_covisible, "n_covisible", 0)
        self.database = KeyframeDatabase(self.vocabulary.score)
        self._lock = threading.Lock()  # the database is shared by tracking, local mapping and loop closing

    # ---- PlaceRecognizer ------------------------------------------------------------------------

    def transform(self, descriptors: NDArray[np.uint8]) -> BowDescription:
        """descriptors: (N, 32) uint8 -> bag of words (L1-normalised TF-IDF) and direct index."""
        return self.vocabulary.transform(descriptors, self.direct_index_level)

    def score(self, a: BowDescription, b: BowDescription) -> float:
        """DBoW2's L1 score in [0, 1]."""
        return self.vocabulary.score(a, b)

    def add(self, keyframe_id: int, bow: BowDescription) -> None:
        with self._lock:
            self.database.add(keyframe_id, bow)

    def remove(self, keyframe_id: int) -> None:
        with self._lock:
            self.database.remove(keyframe_id)

    def query(self, bow: BowDescription, exclude: Sequence[int] = ()) -> list[tuple[int, float]]:
        """Every keyframe sharing a word with ``bow`` (not in ``exclude``) and its score, best first."""
        with self._lock:
            return self.database.query(bow, exclude)

    def vocabulary_identity(self) -> dict[str, object]:
        """The vocabulary's identity (sha256 and sizes, ``Vocabulary.identity``): a saved map's bags of words are
        only valid with the vocabulary that made them (slamkit/map/mapfile.py checks it on load)."""
        return {"name": self.vocabulary_name, **self.vocabulary.identity()}

    # ---- ORB-SLAM's candidate searches -----------------------------------------------------------

    def loop_candidates(
        self, bow: BowDescription, connected: Collection[int], min_score: float, neighbors: NeighborsFn
    ) -> list[tuple[int, float]]:
        """ORB-SLAM's DetectLoopCandidates (see KeyframeDatabase.loop_candidates)."""
        with self._lock:
            return self.database.loop_candidates(
                bow, connected, min_score, neighbors, self.min_common_ratio, self.group_min_ratio, self.n_covisible
            )

    def relocalization_candidates(self, bow: BowDescription, neighbors: NeighborsFn) -> list[tuple[int, float]]:
        """ORB-SLAM's DetectRelocalizationCandidates (see KeyframeDatabase.relocalization_candidates)."""
        with self._lock:
            return self.database.relocalization_candidates(
                bow, neighbors, self.min_common_ratio, self.group_min_ratio, self.n_covisible
            )

    def match(
        self,
        feats1: Features,
        bow1: BowDescription,
        feats2: Features,
        bow2: BowDescription,
        ratio: float,
        mask1: NDArray[np.bool_] | None = None,
        mask2: NDArray[np.bool_] | None = None,
        *,
        max_distance: int,
        rotation_bins: int | None,
    ) -> NDArray[np.int64]:
        """BoW-guided matching through the direct index (see ``slamkit_dbow.matching.match_by_bow``)."""
        return match_by_bow(
            feats1,
            bow1,
            feats2,
            bow2,
            ratio=ratio,
            max_distance=max_distance,
            rotation_bins=rotation_bins,
            mask1=mask1,
            mask2=mask2,
        )

    def candidate_pairs(
        self,
        feats1: Features,
        bow1: BowDescription,
        feats2: Features,
        bow2: BowDescription,
        mask1: NDArray[np.bool_] | None = None,
        mask2: NDArray[np.bool_] | None = None,
        *,
        max_distance: int,
    ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
        """The close pairs of features under the same direct-index node (ORB-SLAM SearchForTriangulation's
        FeatureVector walk; see ``slamkit_dbow.matching.node_pairs``)."""
        return node_pairs(feats1, bow1, feats2, bow2, mask1, mask2, max_distance)
