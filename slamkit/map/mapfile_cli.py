"""``slamkit map info FILE``: what a saved map file holds (issue 17 item 6), after the checks a load makes of the
container (trailer, schema version, sha256); ``slamkit map export`` is left to a later issue."""

from __future__ import annotations

import argparse
import json
from typing import Any

from slamkit.map.mapfile import map_file_info, resolve_map_path


def add_map_parser(sub: Any) -> None:
    """Register ``slamkit map info`` on the command line's subparsers."""
    parser = sub.add_parser("map", help="saved maps: `slamkit map info FILE` (maps, keyframes, points, size, schema)")
    map_sub = parser.add_subparsers(dest="map_command", required=True)
    info = map_sub.add_parser("info", help="what a map file (map.save=FILE) holds, after checking its checksum")
    info.add_argument("file", help="a map file written by `slamkit run map.save=FILE`, or a run directory holding one")
    info.add_argument("--json", action="store_true", help="print JSON instead of text")
    info.set_defaults(func=_info_command)


def _info_command(args: argparse.Namespace) -> int:
    info = map_file_info(resolve_map_path(args.file))
    vocabulary = info.vocabulary or {}
    if args.json:
        out: dict[str, Any] = {
            "file": str(info.path),
            "size_bytes": info.size_bytes,
            "schema_version": info.schema_version,
            "slamkit_version": info.slamkit_version,
            "created_utc": info.created_utc,
            "sha256": info.sha256,
            "vocabulary": info.vocabulary,
            "active_map_id": info.active_map_id,
            "maps": [{"id": m, "keyframes": k, "points": p} for m, k, p in info.maps],
            "keyframes": info.n_keyframes,
            "points": info.n_points,
            "frames": info.n_frames,
        }
        print(json.dumps(out, indent=2))
        return 0
    print(f"file            {info.path}")
    print(f"size            {info.size_bytes} bytes ({info.size_bytes / 2**20:.2f} MiB)")
    print(f"schema version  {info.schema_version} (written by slamkit {info.slamkit_version}, {info.created_utc})")
    print(f"sha256          {info.sha256}")
    if info.vocabulary is None:
        print("vocabulary      none recorded")
    else:
        words = vocabulary.get("words", "?")
        print(f"vocabulary      {vocabulary.get('name', '?')}: {words} words, sha256 {vocabulary.get('sha256', '?')}")
    print(f"maps            {len(info.maps)} ({info.n_keyframes} keyframes, {info.n_points} points)")
    for map_id, n_kfs, n_points in info.maps:
        active = "  (active)" if map_id == info.active_map_id else ""
        print(f"  map {map_id:<4} {n_kfs:>6} keyframes {n_points:>8} points{active}")
    print(f"frames          {info.n_frames} (the sessions' trajectory, each frame relative to a keyframe)")
    return 0
