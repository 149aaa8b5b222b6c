"""``map.save=FILE`` and ``map.load=FILE`` in a run (issue 17 item 3): what app.py calls.

``map.load=FILE``: the run starts with the Atlas saved in FILE (every map, the active one active, ids going on from
the saved ones, keyframes in the keyframe database): a new session (issue 17 item 5). ``map.session_start`` says how
it starts (slamkit/pipeline/tracking/tracker.py, docs/atlas.md "Multi-session"): ``reloc_or_new_map`` (default) a new
map for the session, as ORB-SLAM3's System::LoadAtlas + Atlas::CreateNewMap, unless a frame relocalizes in the loaded
active map while that new map is being initialised; ``new_map`` ORB-SLAM3's exactly; ``relocalize`` the loaded
active map is the session's (tracking starts lost on it; the lost policy of pipeline/lost.py applies). A new map
joins the loaded ones by map merging when the camera comes back to their ground.

``map.save=FILE`` (``true``: ``map.slamkit`` in the run directory): the Atlas is written when the run ends; also
when it fails or is interrupted after it made a map (it keeps what it has; a run that fails before its first
keyframe leaves an existing FILE alone). The two may name the same file: the loaded Atlas, extended, replaces it.
Keys nothing but this module reads are taken out of the ``map`` node before the store is built (``store_node``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from slamkit.errors import ConfigError
from slamkit.interfaces import Camera, PlaceRecognizer
from slamkit.map.atlas import Atlas, StoreFactory
from slamkit.map.mapfile import RUN_DIR_FILE_NAME, MapFileInfo, load_atlas, save_atlas
from slamkit.sensors import FrameRecords

log = logging.getLogger("slamkit")

#: The ``map`` node's keys that configure saving and loading, not the store.
FILE_KEYS = ("save", "load", "session_start")


#: How a session on a loaded Atlas starts (``map.session_start``; slamkit/pipeline/tracking/tracker.py).
SESSION_STARTS = ("reloc_or_new_map", "new_map", "relocalize")


def session_start(map_node: Mapping[str, Any]) -> str:
    """``map.session_start`` (default ``reloc_or_new_map``): how a session on a loaded Atlas starts (Tracker);
    ConfigError for another value."""
    value = map_node.get("session_start")
    start = "reloc_or_new_map" if value in (None, "") else str(value)
    if start not in SESSION_STARTS:
        raise ConfigError(f"map.session_start = {start!r}: expected one of {', '.join(SESSION_STARTS)}")
    return start


def store_node(map_node: Mapping[str, Any]) -> dict[str, Any]:
    """The ``map`` node without ``save`` / ``load`` / ``session_start``: what the store component is built from."""
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
    map_node: Mapping[str, Any],
    atlas: Atlas,
    run_dir: Path,
    config: Mapping[str, Any] | None,
    frames: Callable[[], Mapping[int, FrameRecords]] | None = None,
) -> Iterator[None]:
    """Around the run: on the way out, write the Atlas to ``map.save`` (if set), with ``frames()`` (the runner's
    ``map_frames``: every map's frames, earlier sessions' included) when given. A run that ends normally gets any
    save failure raised (MapFileError); a failed or interrupted run keeps its own exception, and a map it made is still
    saved (a save failure then is logged)."""
    target = save_path(map_node, run_dir)

    def save() -> MapFileInfo:
        assert target is not None
        return save_atlas(atlas, target, config, None if frames is None else frames())

    try:
        yield
    except BaseException:
        if target is not None:
            if any(store.n_keyframes() for _, store in atlas.items()):
                try:
                    info = save()
                    log.warning(
                        "the run failed; the map it made is saved in %s (%d keyframes)", target, info.n_keyframes
                    )
                except Exception as exc:  # the run's own failure is the one to report
                    log.error("the run failed, and saving its map failed too: %s", exc)
            else:
                log.warning("the run failed before it made a map: %s is left as it was", target)
        raise
    if target is not None:
        info = save()
        log.info("map saved in %s: %d keyframes, %d points, %d bytes", target, info.n_keyframes, info.n_points,
                 info.size_bytes)  # fmt: skip


__all__ = ["FILE_KEYS", "SESSION_STARTS", "run_atlas", "save_path", "saving_map", "session_start", "store_node"]
