"""The built-in vocabulary: what ``place=dbow`` uses when no vocabulary file is configured.

No ORB vocabulary can be downloaded, so slamkit trains its own from frames it renders itself (the
synthetic world, ``slamkit.io.synthetic``) with a fixed recipe (``BUILTIN_RECIPE``). The package ships the
result (``vocabularies/<name>.skvoc``); if that file is missing (a stripped install, a source tree without
it), the same recipe is trained on first use and cached under ``$XDG_CACHE_HOME/slamkit`` (default
``~/.cache/slamkit``). Training is deterministic (seeded), so the shipped file and a cache built anywhere
with the same library versions are byte-identical; ``slamkit vocab train --builtin --out FILE`` rebuilds it.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from importlib import resources
from pathlib import Path
from typing import Any

from slamkit_dbow.binformat import BINARY_SUFFIX, read_binary_vocabulary, write_binary_vocabulary
from slamkit_dbow.corpus import SyntheticSource, collect_descriptors, make_extractor
from slamkit_dbow.training import TrainingParams, train_vocabulary
from slamkit_dbow.vocabulary import Vocabulary

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Recipe:
    """Everything that determines a trained vocabulary: training images, extractor and k-means settings."""

    synthetic: tuple[str, ...]  # SyntheticSource texts SCENE:SEED:N_FRAMES
    features: str = "orb"
    n_features: int = 1000
    k: int = 10
    L: int = 4
    seed: int = 0
    max_iterations: int = 50

    def params(self, n_threads: int = 2) -> TrainingParams:
        return TrainingParams(self.k, self.L, self.seed, self.max_iterations, n_threads)

    def sources(self) -> list[SyntheticSource]:
        return [SyntheticSource.parse(s) for s in self.synthetic]

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["synthetic"] = list(self.synthetic)
        return d

    def fingerprint(self) -> str:
        """Short hash of the recipe (names the cache file, so a changed recipe never reads a stale cache)."""
        text = json.dumps(self.as_dict(), sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:12]

    def command(self, out: str) -> str:
        """The ``slamkit vocab train`` command line that trains this recipe."""
        parts = ["slamkit vocab train"]
        parts += [f"--synthetic {s}" for s in self.synthetic]
        parts += [f"--features {self.features}", f"--n-features {self.n_features}", f"--k {self.k}"]
        parts += [f"--levels {self.L}", f"--seed {self.seed}", f"--max-iterations {self.max_iterations}"]
        parts += [f"--out {out}"]
        return " ".join(parts)


#: The recipe of the shipped vocabulary: 4 synthetic scenes x 2 texture seeds x 60 frames = 480 images,
#: ~480k ORB descriptors; k = 10, L = 4 (10,000 words). Texture seeds 1000/1001 differ from the seeds
#: the tests and evaluations use (0, 1, ...), so evaluation scenes are never training images.
BUILTIN_RECIPE = Recipe(
    synthetic=tuple(f"{scene}:{seed}:60" for seed in (1000, 1001) for scene in ("room", "planar", "long_loop", "twins"))
)
BUILTIN_NAME = f"synthetic_orb_k{BUILTIN_RECIPE.k}_L{BUILTIN_RECIPE.L}"


def shipped_vocabulary_path() -> Path:
    """Where the package keeps the built-in vocabulary (the file may be absent)."""
    return Path(str(resources.files("slamkit_dbow"))) / "vocabularies" / f"{BUILTIN_NAME}{BINARY_SUFFIX}"


def cache_dir() -> Path:
    """slamkit's cache folder: $XDG_CACHE_HOME/slamkit, or ~/.cache/slamkit."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "slamkit"


def cached_vocabulary_path(recipe: Recipe = BUILTIN_RECIPE) -> Path:
    return cache_dir() / "vocabularies" / f"{BUILTIN_NAME}-{recipe.fingerprint()}{BINARY_SUFFIX}"


def tick(bar: Any, n: int) -> None:
    """Advance a tqdm bar by n (a callback returning None, for the progress hooks)."""
    bar.update(n)


def train_recipe(recipe: Recipe, progress: bool = False, n_threads: int = 2) -> Vocabulary:
    """Render, extract and train ``recipe`` (deterministic). With ``progress``, tqdm bars on stderr."""
    from tqdm import tqdm

    sources = recipe.sources()
    extractor = make_extractor(recipe.features, {"n_features": recipe.n_features})
    n_images = sum(s.n_frames for s in sources)
    with tqdm(total=n_images, unit="image", desc="features", disable=not progress, dynamic_ncols=True) as bar:
        images = collect_descriptors(sources, [], extractor, on_image=lambda: tick(bar, 1))
    total = recipe.L * sum(a.shape[0] for a in images)
    with tqdm(total=total, unit="desc", unit_scale=True, desc="k-means", disable=not progress) as bar:
        return train_vocabulary(images, recipe.params(n_threads), lambda n: tick(bar, n), {"recipe": recipe.as_dict()})


def load_builtin_vocabulary(
    recipe: Recipe = BUILTIN_RECIPE, shipped: Path | None = None, progress: bool = True
) -> Vocabulary:
    """The built-in vocabulary: the shipped file if present, else the cached one, else trained now (about a
    minute on 2 cores for BUILTIN_RECIPE) and cached. ``shipped`` overrides the shipped file's path."""
    path = shipped_vocabulary_path() if shipped is None else shipped
    if recipe == BUILTIN_RECIPE and path.is_file():
        return read_binary_vocabulary(path)
    cached = cached_vocabulary_path(recipe)
    if cached.is_file():
        return read_binary_vocabulary(cached)
    log.warning("no vocabulary file found: training the built-in vocabulary (once; cached at %s)", cached)
    vocab = train_recipe(recipe, progress=progress)
    cached.parent.mkdir(parents=True, exist_ok=True)
    write_binary_vocabulary(vocab, cached)
    return vocab


def recipe_from_sources(synthetic: Sequence[str], **kwargs: Any) -> Recipe:
    return Recipe(tuple(synthetic), **kwargs)
