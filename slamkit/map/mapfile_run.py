"""``map.save=FILE`` and ``map.load=FILE`` in a run (issue 17 item 3): what app.py calls.

``map.load=FILE``: the run starts with the Atlas saved in FILE (every map, the active one active, ids going on from
the saved ones, keyframes in the keyframe database), and tracking starts lost on it, so the first frames relocalize
against the loaded active map (ORB-SLAM V-C) instead of initialising a new one. Deviation from ORB-SLAM3: its
System::LoadAtlas is followed by Atlas::CreateNewMap, and the new map joins the old ones only by map merging
(issue 17 item 2, not built yet); slamkit relocalizes in the loaded map first. When relocalization keeps failing,
the lost policy acts as on any map (pipeline/lost.py: after ``time_recently_lost_s`` a new map starts and the loaded
one stays in the Atlas; a loaded map of at most ``reset_lost_map_max_keyframes`` keyframes would be reset).

``map.save=FILE`` (``true``: ``map.slamkit`` in the run directory): the Atlas is written when the run ends; also
when it fails or is interrupted after it made a map (it keeps what it has; a run that fails before its first
keyframe leaves an existing FILE alone). The two may name the same file: the loaded Atlas, extended, replaces it.
Keys nothing but this module reads are taken out of the ``map`` node before the store is built (``store_node``).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from slamkit.interfaces import Camera, PlaceRecognizer
from slamkit.map.atlas import Atlas, StoreFactory
from slamkit.map.mapfile import RUN_DIR_FILE_NAME, load_atlas, save_atlas

log = logging.getLogger("slamkit")

#: The ``map`` node's keys that configure saving and loading, not the store.
FILE_KEYS = ("save", "load")


def store_node(map_node: Mapping[str, Any]) -> dict[str, Any]:
    """The ``map`` node without ``save`` / ``load``: what the store component is built from."""
    return {str(k): v for k, v in map_node.items() if k not in FILE_KEYS}


def run_atlas(
    map_node: Mapping[str, Any], new_store: StoreFactory, place: PlaceRecognizer | None, cameras: Sequence[Camera]
) -> Atlas:
    """The run's Atlas: the one saved in ``map.load`` (MapFileError naming the file when it cannot be loaded), else a
    new one. cameras: the run's, reused for saved keyframes with the same calibration."""
    source = map_node.get("load")
    if source in (None, "", False):
        return Atlas(new_store, place)
    atlas = load_atlas(Path(str(source)).expanduser(), new_store, place, cameras)
    n_kfs = sum(store.n_keyframes() for _, store in atlas.items())
    log.info("map.load=%s: %d maps, %d keyframes; active map %d", source, len(atlas), n_kfs, atlas.active_id)
    return atlas


def save_path(map_node: Mapping[str, Any], run_dir: Path) -> Path | None:
    """Where ``map.save`` asks the Atlas to be written (None: nowhere)."""
    target = map_node.get("save")
    if target in (None, "", False):
        return None
    if target is True:
        return run_dir / RUN_DIR_FILE_NAME
    return Path(str(target)).expanduser()


@contextmanager
def saving_map(
    map_node: Mapping[str, Any], atlas: Atlas, run_dir: Path, config: Mapping[str, Any] | None
) -> Iterator[None]:
    """Around the run: on the way out, write the Atlas to ``map.save`` (if set). A run that ends normally gets any
    save failure raised (MapFileError); a failed or interrupted run keeps its own exception, and a map it made is still
    saved (a save failure then is logged)."""
    target = save_path(map_node, run_dir)
    try:
        yield
    except BaseException:
        if target is not None:
            if any(store.n_keyframes() for _, store in atlas.items()):
                try:
                    info = save_atlas(atlas, target, config)
                    log.warning(
                        "the run failed; the map it made is saved in %s (%d keyframes)", target, info.n_keyframes
                    )
                except Exception as exc:  # the run's own failure is the one to report
                    log.error("the run failed, and saving its map failed too: %s", exc)
            else:
                log.warning("the run failed before it made a map: %s is left as it was", target)
        raise
    if target is not None:
        info = save_atlas(atlas, target, config)
        log.info("map saved in %s: %d keyframes, %d points, %d bytes", target, info.n_keyframes, info.n_points,
                 info.size_bytes)  # fmt: skip


__all__ = ["FILE_KEYS", "run_atlas", "save_path", "saving_map", "store_node"]
