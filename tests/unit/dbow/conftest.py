"""Fixtures of the bag-of-words tests: descriptors of rendered synthetic frames and small vocabularies."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray
from slamkit_dbow.corpus import SyntheticSource, collect_descriptors, make_extractor
from slamkit_dbow.training import TrainingParams, train_vocabulary
from slamkit_dbow.vocabulary import Vocabulary

from slamkit.interfaces import FeatureExtractor


@pytest.fixture(scope="session")
def orb() -> FeatureExtractor:
    """slamkit's ``features=orb`` with its default config (1000 features)."""
    return make_extractor("orb")


@pytest.fixture(scope="session")
def room_descriptors(orb: FeatureExtractor) -> list[NDArray[np.uint8]]:
    """ORB descriptors of 12 frames of the synthetic room (texture seed 1000)."""
    return collect_descriptors([SyntheticSource("room", 1000, 12)], [], orb)


@pytest.fixture(scope="session")
def small_vocab(room_descriptors: list[NDArray[np.uint8]]) -> Vocabulary:
    """k=6, L=3 vocabulary trained on the 12 room frames (up to 216 words)."""
    return train_vocabulary(room_descriptors, TrainingParams(k=6, L=3, seed=3))


@pytest.fixture(scope="session")
def builtin_vocab() -> Vocabulary:
    """The vocabulary slamkit ships (trained on first use if the file is absent)."""
    from slamkit_dbow.builtin import load_builtin_vocabulary

    return load_builtin_vocabulary()
