"""Training images for a vocabulary and their descriptors: frames rendered by slamkit's synthetic world,
and image files from folders. Descriptors come from a registered feature extractor (``features=orb`` by
default, built from its plugin config node through the component registry)."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from slamkit.errors import ConfigError, DatasetError
from slamkit.interfaces import FeatureExtractor
from slamkit.plugins import ComponentRegistry

#: Image file extensions read from training folders.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pgm", ".ppm", ".bmp", ".tif", ".tiff")


@dataclass(frozen=True)
class SyntheticSource:
    """``n_frames`` frames evenly spaced over the whole sequence of synthetic scene ``scene`` rendered with
    texture seed ``seed`` (slamkit.io.synthetic; 640 x 480, the dataset's default pixel noise)."""

    scene: str
    seed: int
    n_frames: int

    @staticmethod
    def parse(text: str) -> SyntheticSource:
        """'SCENE:SEED:N_FRAMES', e.g. 'long_loop:1000:60'."""
        parts = text.split(":")
        try:
            if len(parts) != 3:
                raise ValueError
            src = SyntheticSource(parts[0], int(parts[1]), int(parts[2]))
        except ValueError:
            raise ConfigError(f"--synthetic {text!r}: expected SCENE:SEED:N_FRAMES, e.g. long_loop:1000:60") from None
        if src.n_frames < 1:
            raise ConfigError(f"--synthetic {text!r}: N_FRAMES must be >= 1")
        return src

    def __str__(self) -> str:
        return f"{self.scene}:{self.seed}:{self.n_frames}"

    def images(self) -> Iterator[NDArray[np.uint8]]:
        from slamkit.io.synthetic.dataset import SyntheticDataset

        ds = SyntheticDataset(scene=self.scene, seed=self.seed, imu=False, depth=False)
        n = len(ds)
        for i in np.unique(np.linspace(0, n - 1, min(self.n_frames, n)).round().astype(int)):
            yield ds[int(i)].image


def image_files(folders: Sequence[str | Path]) -> list[Path]:
    """Every image file under the folders (recursively), sorted by path within each folder."""
    files: list[Path] = []
    for folder in folders:
        root = Path(folder)
        if not root.is_dir():
            raise DatasetError(f"{root}: training image folder not found")
        found = sorted(p for p in root.rglob("*") if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
        if not found:
            raise DatasetError(f"{root}: no image file ({', '.join(IMAGE_SUFFIXES)}) in this folder")
        files.extend(found)
    return files


def read_grey(path: Path) -> NDArray[np.uint8]:
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise DatasetError(f"{path}: cannot read this image file")
    return np.asarray(image, np.uint8)


def make_extractor(name: str = "orb", overrides: dict[str, Any] | None = None) -> FeatureExtractor:
    """The registered feature extractor ``features=<name>`` with its default config plus ``overrides``."""
    registry = ComponentRegistry.discover()
    node = {**registry.get("features", name).config_node(), **(overrides or {})}
    extractor: FeatureExtractor = registry.instantiate("features", node)
    return extractor


def collect_descriptors(
    synthetic: Sequence[SyntheticSource],
    files: Sequence[Path],
    extractor: FeatureExtractor,
    on_image: Callable[[], None] | None = None,
) -> list[NDArray[np.uint8]]:
    """One (N_j, 32) uint8 descriptor array per training image: synthetic frames first (in the given
    order), then the files."""

    def images() -> Iterator[NDArray[np.uint8]]:
        for src in synthetic:
            yield from src.images()
        for f in files:
            yield read_grey(f)

    out = []
    for image in images():
        out.append(np.ascontiguousarray(extractor.extract(image).descriptors, np.uint8))
        if on_image is not None:
            on_image()
    return out
