"""slamkit_dbow: DBoW2-style bag of binary words for slamkit (first-party plugin, ``place=dbow``).

- vocabulary.py: the vocabulary tree, ``transform`` (bag of words + direct index) and the L1 score;
- training.py / kernels.py: hierarchical k-means (k-means++ seeds, bitwise-majority centres), TF-IDF;
- textformat.py / binformat.py / files.py: DBoW2's text format (ORBvoc.txt) and slamkit's binary form;
- builtin.py: the vocabulary slamkit ships (trained on its synthetic world), rebuilt on first use if absent;
- database.py / covisibility.py: ORB-SLAM's keyframe database and covisibility grouping (III-E);
- matching.py: BoW-guided matching (SearchByBoW) and triangulation candidates (SearchForTriangulation's node walk);
  recognizer.py: the ``place=dbow`` component;
- cli.py: ``slamkit vocab train | convert | info | eval`` (also ``python -m slamkit_dbow vocab ...``).
See docs/place_recognition.md.
"""

from slamkit_dbow.covisibility import group_by_covisibility
from slamkit_dbow.database import KeyframeDatabase
from slamkit_dbow.files import load_vocabulary, save_vocabulary
from slamkit_dbow.matching import match_by_bow, node_pairs
from slamkit_dbow.recognizer import DbowPlaceRecognizer
from slamkit_dbow.training import TrainingParams, train_vocabulary
from slamkit_dbow.vocabulary import Vocabulary, VocabularyError

__all__ = [
    "DbowPlaceRecognizer",
    "KeyframeDatabase",
    "TrainingParams",
    "Vocabulary",
    "VocabularyError",
    "group_by_covisibility",
    "load_vocabulary",
    "match_by_bow",
    "node_pairs",
    "save_vocabulary",
    "train_vocabulary",
]
