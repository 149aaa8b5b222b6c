"""``slamkit export SOURCE --format ply|colmap|tum --out PATH``: a run's map as a PLY point cloud, a COLMAP text
model or a TUM keyframe trajectory (slamkit/export/__init__.py, docs/export.md).

SOURCE is a map file or a run directory holding one (``MAP_FILE_NAMES``); the points take their colours from the
keyframes' images, read again from the dataset the run's config names (the run directory's config.yaml, else the
config the map file records). ``--no-colours`` skips that (every point mid grey).

The map file is slamkit's (slamkit/map/mapfile.py, docs/atlas.md "Saved maps").
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from slamkit.errors import ExportError, SlamkitError
from slamkit.map.atlas import Atlas
from slamkit.map.mapfile import read_atlas, read_manifest

from . import FORMATS, default_maps, export_map
from .colours import DatasetImages, FrameImages, dataset_for_colours
from .snapshot import select_maps

#: The names of the map file a run directory may hold (``map.save=FILE`` of issue 17), first found wins.
MAP_FILE_NAMES = ("map.slamkit",)


@dataclass(frozen=True)
class ExportSource:
    """What ``slamkit export`` exports: the Atlas read from ``path``, and the run's resolved config (None: unknown),
    whose dataset the colours come from."""

    path: Path
    atlas: Atlas
    config: Mapping[str, Any] | None


def read_map_file(path: Path) -> tuple[Atlas, Mapping[str, Any] | None]:
    """(the Atlas, the config that built it) of a slamkit map file (slamkit/map/mapfile.py: ``read_atlas`` builds
    in-memory stores and no keyframe database — the export needs no vocabulary —; the manifest holds the run's
    config). Its MapFileError names the file and the fault."""
    atlas: Atlas = read_atlas(path)
    config = read_manifest(path).get("config")
    return atlas, config if isinstance(config, Mapping) else None


def _run_config(run_dir: Path) -> Mapping[str, Any] | None:
    """A run directory's resolved config (config.yaml), None when it has none."""
    path = run_dir / "config.yaml"
    if not path.is_file():
        return None
    import yaml

    try:
        config = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ExportError(f"{path}: the run's config cannot be read ({exc})") from exc
    return config if isinstance(config, dict) else None


def load_export_source(path: Path) -> ExportSource:
    """SOURCE of ``slamkit export``: a map file, or a run directory holding one of ``MAP_FILE_NAMES``."""
    if path.is_dir():
        found = [path / name for name in MAP_FILE_NAMES if (path / name).is_file()]
        if not found:
            raise ExportError(
                f"{path}: no map file in this run directory (looked for {', '.join(MAP_FILE_NAMES)}; a run saves "
                "its map with map.save=FILE)"
            )
        atlas, file_config = read_map_file(found[0])
        return ExportSource(path, atlas, _run_config(path) or file_config)
    if path.is_file():
        atlas, file_config = read_map_file(path)
        return ExportSource(path, atlas, file_config)
    raise ExportError(f"{path}: no such map file or run directory")


def _colours(source: ExportSource) -> FrameImages | None:
    """The run's frame images, or None (and a note on stderr) when the run's dataset cannot be opened again."""
    if source.config is None:
        print(f"slamkit export: {source.path}: no run config, so no images: points are grey", file=sys.stderr)
        return None
    try:
        return DatasetImages(dataset_for_colours(source.config))
    except SlamkitError as exc:
        print(f"slamkit export: the run's dataset cannot be read again ({exc}): points are grey", file=sys.stderr)
        return None


def _maps_arg(text: str) -> str | int:
    if text in ("all", "main"):
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected all, main or a map id") from None


def add_export_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register the ``export`` subcommand on an argparse ``_SubParsersAction`` and return its parser."""
    p: argparse.ArgumentParser = subparsers.add_parser(
        "export",
        help="a run's map as a PLY point cloud, a COLMAP text model or a TUM keyframe trajectory",
        description=(
            "Export the map of SOURCE (a map file, or a run directory holding one): ply = the map points with "
            "their colours and map id; colmap = cameras.txt, images.txt, points3D.txt (one model folder per map); "
            "tum = the keyframe trajectory."
        ),
    )
    p.add_argument("source", type=Path, metavar="SOURCE", help="a map file or a run directory holding one")
    p.add_argument("--format", required=True, choices=FORMATS, dest="fmt", help="ply, colmap or tum")
    p.add_argument("--out", required=True, type=Path, metavar="PATH", help="the file (ply, tum) or folder (colmap)")
    p.add_argument(
        "--map",
        type=_maps_arg,
        default=None,
        dest="maps",
        metavar="all|main|ID",
        help="which maps: all (default for ply), main (the one with the most keyframes; default for colmap and "
        "tum) or a map id",
    )
    p.add_argument(
        "--images",
        type=Path,
        default=None,
        metavar="DIR",
        help="colmap: also write the keyframes' images into DIR (frame_NNNNNN.png, the names images.txt uses)",
    )
    p.add_argument("--no-colours", action="store_true", help="do not read the run's images: every point grey")
    p.set_defaults(func=run_export)
    return p


def run_export(args: argparse.Namespace) -> int:
    """The ``export`` subcommand: 0 when written; a slamkit error is printed by the CLI as one line, exit 2."""
    source = load_export_source(args.source)
    select_maps(
        source.atlas, default_maps(args.fmt) if args.maps is None else args.maps
    )  # errors before reading images
    needs_images = args.fmt != "tum" and not args.no_colours
    colours = _colours(source) if needs_images or args.images is not None else None
    if args.images is not None and colours is None:
        raise ExportError(f"--images {args.images}: the run's images cannot be read, none written")
    result = export_map(source.atlas, args.fmt, args.out, colours=colours, maps=args.maps, images_dir=args.images)
    print(result.summary())
    return 0
