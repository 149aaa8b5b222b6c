"""Per-call time and retained memory of the bag-of-words calls the pipeline makes (issue 15: the bag of words as
arrays must not slow tracking, local mapping or loop closing down).

Usage: python benchmarks/bow_calls.py [--frames 60] [--repeats 7]

Descriptors: ORB (``features=orb``, 1000 per image) of every 4th of the first ``--frames`` * 4 frames of the synthetic
room; the built-in vocabulary, direct index at depth 2 (place=dbow's defaults). Times the calls with the public API
only (so the script runs on any revision): ``transform``; ``score`` of every pair of images; the keyframe database's
``add`` of every image then ``loop_candidates``-style ``query`` (ORB-SLAM's 0.8 common-word ratio) of each, and
``remove``; ``match_by_bow`` (SearchByBoW: ORB-SLAM's 0.75 ratio, TH_LOW 50, 30 rotation bins) and ``node_pairs``
(SearchForTriangulation's candidates) of consecutive images. Prints each call's best-of-``--repeats`` mean per call,
microseconds, and the memory one bag of words keeps (tracemalloc, after a warm-up).
"""

from __future__ import annotations

import argparse
import time
import tracemalloc
from collections.abc import Callable

import numpy as np
from slamkit_dbow.builtin import load_builtin_vocabulary
from slamkit_dbow.corpus import make_extractor
from slamkit_dbow.database import KeyframeDatabase
from slamkit_dbow.matching import match_by_bow, node_pairs

from slamkit.io.synthetic.dataset import SyntheticDataset


def best_mean_us(fn: Callable[[], object], calls: int, repeats: int) -> float:
    """Best over ``repeats`` of the mean time of one call of ``fn`` (which makes ``calls`` calls), microseconds."""
    fn()
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, (time.perf_counter() - t0) / calls)
    return best * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    ds = SyntheticDataset(scene="room", seed=0, imu=False, depth=False)
    orb = make_extractor("orb")
    feats = [orb.extract(ds[4 * i].image) for i in range(args.frames)]
    vocab = load_builtin_vocabulary()
    bows = [vocab.transform(f.descriptors, 2) for f in feats]
    n = len(bows)
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]

    def add_all() -> KeyframeDatabase:
        db = KeyframeDatabase(vocab.score)
        for k, b in enumerate(bows):
            db.add(k, b)
        return db

    db = add_all()

    def remove_all() -> None:
        d = add_all()
        for k in range(n):
            d.remove(k)

    t_add = best_mean_us(add_all, n, args.repeats)
    rows = {
        "transform": best_mean_us(lambda: [vocab.transform(f.descriptors, 2) for f in feats], n, args.repeats),
        "score": best_mean_us(lambda: [vocab.score(bows[i], bows[j]) for i, j in pairs], len(pairs), args.repeats),
        "database add": t_add,
        "database remove": best_mean_us(remove_all, n, args.repeats) - t_add,
        "database query (0.8)": best_mean_us(
            lambda: [db.query(b, exclude=[k], min_common_ratio=0.8) for k, b in enumerate(bows)], n, args.repeats
        ),
        "match_by_bow": best_mean_us(
            lambda: [match_by_bow(feats[i], bows[i], feats[i + 1], bows[i + 1], 0.75, 50, 30) for i in range(n - 1)],
            n - 1,
            args.repeats,
        ),
        "node_pairs": best_mean_us(
            lambda: [node_pairs(feats[i], bows[i], feats[i + 1], bows[i + 1], None, None, 50) for i in range(n - 1)],
            n - 1,
            args.repeats,
        ),
    }
    checksum = sum(vocab.score(bows[i], bows[j]) for i, j in pairs)
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    kept = [vocab.transform(f.descriptors, 2) for f in feats]
    per_bow = (tracemalloc.get_traced_memory()[0] - before) / len(kept)
    tracemalloc.stop()
    words = np.mean([len(b.words) for b in bows])
    print(f"{n} images, {words:.0f} words each on average; score checksum {checksum!r}")
    for name, us in rows.items():
        print(f"{name:22s} {us:9.1f} us per call")
    print(f"one bag of words keeps {per_bow / 1024:.1f} KiB (tracemalloc)")


if __name__ == "__main__":
    main()
