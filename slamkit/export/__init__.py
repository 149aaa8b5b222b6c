"""Map export (issue 18): the map points as a PLY point cloud, the keyframes and points as a COLMAP text model,
the keyframe trajectory as a TUM file. ``slamkit export SOURCE --format ply|colmap|tum --out PATH`` is the command
(slamkit/export/cli.py); :func:`export_map` the function behind it. docs/export.md describes the files.

Exporters read the map through the MapStore protocol, under each map's read lock, into a snapshot
(slamkit/export/snapshot.py) and write from it; colours come from the keyframes' images read again from the
dataset (slamkit/export/colours.py says why).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from slamkit.errors import ExportError
from slamkit.interfaces import MapStore
from slamkit.map.atlas import Atlas

from .colmap import write_colmap_model, write_keyframe_images
from .colours import DatasetImages, FrameImages, point_colours
from .ply import write_ply
from .snapshot import MapSnapshot, snapshot_atlas
from .tum import write_tum

#: The formats of ``export_map`` / ``slamkit export --format``.
FORMATS = ("ply", "colmap", "tum")


@dataclass
class ExportResult:
    """What an export wrote: paths (the files or model folders), per exported map its id, keyframes and points."""

    fmt: str
    paths: list[Path] = field(default_factory=list)
    maps: list[tuple[int, int, int]] = field(default_factory=list)  # (map id, keyframes, points)
    images_written: int = 0

    def summary(self) -> str:
        maps = "; ".join(f"map {m}: {k} keyframes, {p} points" for m, k, p in self.maps) or "no map"
        where = ", ".join(str(p) for p in self.paths)
        extra = f"; {self.images_written} keyframe images" if self.images_written else ""
        return f"{self.fmt}: {maps}{extra} -> {where}"


def default_maps(fmt: str) -> str:
    # a PLY holds every map (its map_id property tells them apart); a COLMAP model or a TUM file is one world frame
    return "all" if fmt == "ply" else "main"


def export_map(
    source: Atlas | MapStore,
    fmt: str,
    out: str | Path,
    colours: FrameImages | None = None,
    maps: str | int | Sequence[int] | None = None,
    images_dir: str | Path | None = None,
) -> ExportResult:
    """Export the maps of ``source`` (an Atlas, or one MapStore) as ``fmt`` at ``out``.

    fmt: "ply" (``out`` is the file), "colmap" (``out`` is the model folder; with several maps, one folder
    ``out/<map id>`` per map) or "tum" (``out`` is the file; with several maps, ``out/<map id>.tum``).
    colours: the run's frame images (e.g. ``DatasetImages(dataset)``) that points take their colour from; None: every
    point mid grey. maps: "all" (every map with a keyframe), "main" (the map with the most keyframes, the one of the
    run's keyframes.tum), a map id or ids; default: "all" for PLY, "main" for COLMAP and TUM. images_dir: COLMAP only,
    also write the keyframes' images there (needs ``colours``). ExportError for an unknown format or map, or an
    output that cannot be written.
    """
    if fmt not in FORMATS:
        raise ExportError(f"format {fmt!r}: expected one of {', '.join(FORMATS)}")
    if images_dir is not None and (fmt != "colmap" or colours is None):
        raise ExportError("images_dir: keyframe images are written with the COLMAP format, from a run's images")
    out = Path(out)
    snaps = snapshot_atlas(source, default_maps(fmt) if maps is None else maps)
    if not snaps or all(len(s.keyframes) == 0 for s in snaps):
        raise ExportError(f"{out}: nothing to export, the map has no keyframe")
    result = ExportResult(fmt, maps=[(s.map_id, len(s.keyframes), s.n_points) for s in snaps])
    if fmt == "tum":
        for snap in snaps:
            result.paths.append(write_tum(out if len(snaps) == 1 else out / f"{snap.map_id}.tum", snap))
        return result
    rgb = point_colours(snaps, colours)
    if fmt == "ply":
        result.paths.append(write_ply(out, snaps, rgb))
        return result
    for snap, snap_rgb in zip(snaps, rgb, strict=True):
        result.paths.append(write_colmap_model(out if len(snaps) == 1 else out / str(snap.map_id), snap, snap_rgb))
    if images_dir is not None and colours is not None:
        result.images_written = write_keyframe_images(Path(images_dir), snaps, colours)
    return result


__all__ = ["FORMATS", "DatasetImages", "ExportResult", "FrameImages", "MapSnapshot", "export_map"]
