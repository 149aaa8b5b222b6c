"""Time of ``transform`` (bag of words + direct index) of 1000 ORB descriptors, the budget of issue 5: < 5 ms.

Usage: python benchmarks/bow_transform.py [--repeats 200] [--json results.json]

Vocabularies: slamkit's built-in one (k=10, L=4, 10,000 words) and a full k=10, L=6 tree (1.1 M nodes,
10^6 words: the shape of ORB-SLAM's ORBvoc.txt) with random node descriptors and unit weights, which
costs the same descent (6 levels x 10 Hamming distances per feature). Descriptors: the 1000 ORB features
(``features=orb``) of a frame of the synthetic room. Prints the median and 90th percentile wall time (ms)
of ``DbowPlaceRecognizer.transform`` (direct index at depth 2) over ``--repeats`` calls after a warm-up.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from slamkit_dbow.builtin import load_builtin_vocabulary
from slamkit_dbow.corpus import make_extractor
from slamkit_dbow.recognizer import DbowPlaceRecognizer
from slamkit_dbow.vocabulary import Vocabulary

from slamkit.io.synthetic.dataset import SyntheticDataset


def full_tree(k: int, L: int, seed: int = 0) -> Vocabulary:
    """A complete k-ary tree of depth L with random node descriptors (ORBvoc's shape for k=10, L=6)."""
    rng = np.random.default_rng(seed)
    n = (k ** (L + 1) - 1) // (k - 1)
    parent = np.concatenate(([-1], (np.arange(1, n) - 1) // k)).astype(np.int32)
    desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    is_leaf = np.zeros(n, bool)
    is_leaf[n - k**L :] = True
    return Vocabulary(k, L, parent, desc, is_leaf.astype(np.float64), is_leaf)


def time_transform(recognizer: DbowPlaceRecognizer, desc: np.ndarray, repeats: int) -> dict[str, float]:
    for _ in range(5):
        recognizer.transform(desc)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        recognizer.transform(desc)
        times.append((time.perf_counter() - t0) * 1e3)
    return {"median_ms": float(np.median(times)), "p90_ms": float(np.percentile(times, 90))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=200)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    image = SyntheticDataset(scene="room", seed=0, imu=False, depth=False)[60].image
    desc = make_extractor("orb").extract(image).descriptors
    print(f"{desc.shape[0]} ORB descriptors; {args.repeats} transforms each")
    results = {}
    for name, vocab in (
        ("builtin k=10 L=4", load_builtin_vocabulary()),
        ("full k=10 L=6 (ORBvoc shape)", full_tree(10, 6)),
    ):
        r = time_transform(DbowPlaceRecognizer(vocabulary_object=vocab), desc, args.repeats)
        results[name] = {**r, "n_words": vocab.n_words, "n_descriptors": int(desc.shape[0])}
        print(f"{name:30s} {vocab.n_words:>9,d} words  median {r['median_ms']:.3f} ms  p90 {r['p90_ms']:.3f} ms")
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
