"""``slamkit vocab train | convert | info | eval``: train, convert, inspect and evaluate vocabularies.

The core CLI does not import plugins; ``add_vocab_parser(subparsers)`` registers the ``vocab`` command on
any argparse sub-parser set (handler: ``args.func``), and ``python -m slamkit_dbow vocab ...`` runs it
standalone. Exit codes: 0 success, 2 bad input (one line on stderr).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from slamkit.errors import ConfigError, SlamkitError
from slamkit_dbow.builtin import BUILTIN_RECIPE, Recipe, load_builtin_vocabulary, tick, train_recipe
from slamkit_dbow.files import load_vocabulary, save_vocabulary
from slamkit_dbow.vocabulary import Vocabulary

EXIT_OK = 0
EXIT_BAD_INPUT = 2


def _add_train(sub: Any) -> None:
    p = sub.add_parser(
        "train",
        help="train a vocabulary (hierarchical k-means + TF-IDF) from images and/or synthetic frames",
        description=(
            "Extract features from every training image and train a DBoW2 vocabulary tree. The output format "
            "follows --out: *.txt / *.txt.gz is DBoW2's text format (ORBvoc.txt), anything else slamkit's "
            "binary form (.skvoc). --builtin trains the recipe of the vocabulary slamkit ships."
        ),
    )
    p.add_argument("--images", nargs="+", action="extend", default=[], metavar="DIR", help="folders of images")
    p.add_argument(
        "--synthetic",
        nargs="+",
        action="extend",
        default=[],
        metavar="SCENE:SEED:N",
        help="N frames evenly spaced over synthetic scene SCENE rendered with texture seed SEED",
    )
    p.add_argument("--builtin", action="store_true", help="train the built-in recipe (no other source allowed)")
    p.add_argument("--out", required=True, type=Path, metavar="FILE", help="output vocabulary file")
    p.add_argument("--features", default="orb", help="registered feature extractor (default: orb)")
    p.add_argument("--n-features", type=int, default=1000, help="features per image (default: 1000)")
    p.add_argument("--k", type=int, default=10, help="branching factor (default: 10; DBoW2/ORB-SLAM: 10)")
    p.add_argument("--levels", type=int, default=4, help="depth L (default: 4; ORB-SLAM's ORBvoc: 6)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the k-means++ seeding (default: 0)")
    p.add_argument("--max-iterations", type=int, default=50, help="cap on k-means iterations per node")
    p.add_argument("--threads", type=int, default=2, help="clustering threads (result does not depend on it)")
    p.add_argument("--text-precision", type=int, default=None, help="digits of text weights (default: exact)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=run_train)


def run_train(args: argparse.Namespace) -> int:
    if args.builtin:
        if args.images or args.synthetic:
            raise ConfigError("vocab train: --builtin takes no --images/--synthetic (it has its own recipe)")
        recipe = BUILTIN_RECIPE
    else:
        recipe = Recipe(
            tuple(args.synthetic), args.features, args.n_features, args.k, args.levels, args.seed, args.max_iterations
        )
        if not args.images and not args.synthetic:
            raise ConfigError("vocab train: give training images with --images DIR... and/or --synthetic SCENE:SEED:N")
    t0 = time.perf_counter()
    if args.images:
        vocab = _train_with_images(recipe, [Path(d) for d in args.images], not args.no_progress, args.threads)
    else:
        vocab = train_recipe(recipe, progress=not args.no_progress, n_threads=args.threads)
    save_vocabulary(vocab, args.out, args.text_precision)
    elapsed = time.perf_counter() - t0
    meta = vocab.metadata
    print(
        f"{args.out}: {vocab!r}, trained on {meta.get('n_images')} images / {meta.get('n_descriptors')} descriptors "
        f"in {elapsed:.1f} s"
    )
    return EXIT_OK


def _train_with_images(recipe: Recipe, folders: list[Path], progress: bool, n_threads: int) -> Vocabulary:
    from tqdm import tqdm

    from slamkit_dbow.corpus import collect_descriptors, image_files, make_extractor
    from slamkit_dbow.training import train_vocabulary

    files = image_files(folders)
    sources = recipe.sources()
    extractor = make_extractor(recipe.features, {"n_features": recipe.n_features})
    total = sum(s.n_frames for s in sources) + len(files)
    with tqdm(total=total, unit="image", desc="features", disable=not progress, dynamic_ncols=True) as bar:
        images = collect_descriptors(sources, files, extractor, on_image=lambda: tick(bar, 1))
    meta = {"recipe": {**recipe.as_dict(), "images": [str(f) for f in folders], "n_image_files": len(files)}}
    work = recipe.L * sum(a.shape[0] for a in images)
    with tqdm(total=work, unit="desc", unit_scale=True, desc="k-means", disable=not progress) as bar:
        return train_vocabulary(images, recipe.params(n_threads), lambda n: tick(bar, n), meta)


def _load(spec: str) -> Vocabulary:
    return load_builtin_vocabulary() if spec == "builtin" else load_vocabulary(spec)


def run_convert(args: argparse.Namespace) -> int:
    vocab = _load(args.input)
    save_vocabulary(vocab, args.output, args.text_precision)
    print(f"{args.output}: {vocab!r}")
    return EXIT_OK


def run_info(args: argparse.Namespace) -> int:
    vocab = _load(args.vocabulary)
    info = {
        "k": vocab.k,
        "L": vocab.L,
        "scoring": vocab.scoring.name,
        "weighting": vocab.weighting.name,
        "n_words": vocab.n_words,
        "n_nodes": vocab.n_nodes,
        "descriptor_bytes": vocab.descriptor_bytes,
        "metadata": vocab.metadata,
    }
    print(json.dumps(info, indent=2))
    return EXIT_OK


def run_eval(args: argparse.Namespace) -> int:
    from slamkit_dbow.corpus import make_extractor
    from slamkit_dbow.evaluation import real_sequences, retrieval_precision, synthetic_sequence

    vocab = _load(args.vocabulary)
    extractor = make_extractor("orb")
    rows: list[dict[str, Any]] = []

    def add(name: str, what: str, r: Any) -> None:
        rows.append(
            {
                "sequence": name,
                "test": what,
                "queries": r.n_queries,
                "precision": r.precision,
                "within_1m": r.n_near / max(r.n_queries, 1),
                "margin": r.margin,
            }
        )
        print(
            f"{name:30s} {what:30s} {r.n_queries:4d} queries  top-1 right {r.precision:6.1%}  "
            f"within 1 m {r.n_near / max(r.n_queries, 1):6.1%}  margin {r.margin:.2f}"
        )

    for scene in args.scenes:
        seq = synthetic_sequence(scene, args.seed, extractor)
        add(seq.name, "neighbour (kf every 1 s)", retrieval_precision(vocab, seq.descriptors, seq.T_w_c, step=2))
        if scene in ("long_loop", "twins", "room", "planar"):
            from slamkit.io.synthetic.scenes import build_scene

            period = build_scene(scene).path.period_s
            q = [i for i in range(len(seq.descriptors)) if i * 15 / 30.0 > period + 0.5]
            if q:
                excl = int(period / 2)  # keyframes of the last half loop are not loop candidates
                r = retrieval_precision(vocab, seq.descriptors, seq.T_w_c, 2, q, exclude_recent=excl)
                add(seq.name, "loop (revisit after a loop)", r)
    if args.datasets is not None:
        for seq, step in real_sequences(Path(args.datasets), extractor):
            add(
                seq.name,
                f"neighbour (kf every {step} frames)",
                retrieval_precision(vocab, seq.descriptors, seq.T_w_c, step),
            )
    if args.json is not None:
        args.json.write_text(json.dumps({"vocabulary": args.vocabulary, "results": rows}, indent=2))
    return EXIT_OK


def add_vocab_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``vocab`` (train | convert | info | eval) on an argparse ``_SubParsersAction``."""
    vocab: argparse.ArgumentParser = subparsers.add_parser(
        "vocab", help="bag-of-words vocabularies: train | convert | info | eval"
    )
    sub = vocab.add_subparsers(dest="vocab_command", required=True)
    _add_train(sub)
    conv = sub.add_parser("convert", help="convert between DBoW2 text (*.txt, *.txt.gz) and slamkit binary")
    conv.add_argument("input", help="vocabulary file, or 'builtin'")
    conv.add_argument("output", type=Path, help="output file (format from its name)")
    conv.add_argument("--text-precision", type=int, default=None, help="digits of text weights (default: exact)")
    conv.set_defaults(func=run_convert)
    info = sub.add_parser("info", help="print a vocabulary's k, L, sizes and provenance as JSON")
    info.add_argument("vocabulary", help="vocabulary file, or 'builtin'")
    info.set_defaults(func=run_info)
    ev = sub.add_parser("eval", help="top-1 place-retrieval precision on synthetic scenes and real images")
    ev.add_argument("--vocabulary", default="builtin", help="vocabulary file, or 'builtin' (default)")
    ev.add_argument("--scenes", nargs="*", default=["room", "planar", "long_loop", "twins"])
    ev.add_argument("--seed", type=int, default=0, help="texture seed of the evaluation scenes (default: 0)")
    ev.add_argument("--datasets", type=Path, default=None, help="the shared datasets folder (real images)")
    ev.add_argument("--json", type=Path, default=None, help="write the results as JSON")
    ev.set_defaults(func=run_eval)
    return vocab


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m slamkit_dbow vocab ...``."""
    parser = argparse.ArgumentParser(prog="python -m slamkit_dbow")
    add_vocab_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except SlamkitError as exc:
        print(f"slamkit vocab {args.vocab_command}: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
