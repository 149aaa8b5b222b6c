"""The viewer's settings, read from the run's composed config (the ``viewer`` group, conf/viewer/rerun.yaml)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from slamkit.errors import ConfigError


@dataclass(frozen=True)
class ViewerSettings:
    """save: record to this .rrd file (no display); connect: stream to a rerun viewer already running at this URL;
    neither: spawn a viewer. image_every: log every n-th frame's image (frames). jpeg_quality: 1-100.
    skip_stale_frames: when the viewer's thread falls behind, a frame with newer frames waiting is drawn without its
    image and features (False: every frame is drawn, however long it takes). process: draw in a child process (True)
    or in a thread of the run's process. niceness: how much the child process lowers its priority (Linux)."""

    save: Path | None
    connect: str | None
    image_every: int
    jpeg_quality: int
    skip_stale_frames: bool = True
    process: bool = True
    niceness: int = 10

    @classmethod
    def from_config(cls, config: Mapping[str, Any]) -> ViewerSettings | None:
        """The settings of ``config["viewer"]`` when it selects this viewer (``kind: rerun``), else None."""
        node = config.get("viewer")
        if not isinstance(node, Mapping) or node.get("kind") != "rerun":
            return None
        image_every = node.get("image_every", 1)
        if isinstance(image_every, bool) or not isinstance(image_every, int) or image_every < 1:
            raise ConfigError(f"viewer.image_every = {image_every!r}: expected an integer >= 1 (frames)")
        quality = node.get("jpeg_quality", 80)
        if isinstance(quality, bool) or not isinstance(quality, int) or not 1 <= quality <= 100:
            raise ConfigError(f"viewer.jpeg_quality = {quality!r}: expected an integer in [1, 100]")
        skip_stale = node.get("skip_stale_frames", True)
        if not isinstance(skip_stale, bool):
            raise ConfigError(f"viewer.skip_stale_frames = {skip_stale!r}: expected true or false")
        process = node.get("process", True)
        if not isinstance(process, bool):
            raise ConfigError(f"viewer.process = {process!r}: expected true or false")
        niceness = node.get("niceness", 10)
        if isinstance(niceness, bool) or not isinstance(niceness, int) or not 0 <= niceness <= 19:
            raise ConfigError(f"viewer.niceness = {niceness!r}: expected an integer in [0, 19]")
        save = node.get("save")
        connect = node.get("connect")
        if save is not None and connect is not None:
            raise ConfigError("viewer.save and viewer.connect are both set: record to a file or stream, not both")
        return cls(
            save=None if save is None else Path(str(save)),
            connect=None if connect is None else str(connect),
            image_every=image_every,
            jpeg_quality=quality,
            skip_stale_frames=skip_stale,
            process=process,
            niceness=niceness,
        )
