"""Where the exported points get their colours: the keyframes' images, read again from the dataset.

Keyframes do not keep their images. The exporters re-read the frames the keyframes were made from (each
keyframe knows its ``frame_index``) through the dataset the run used, built again from the run's config, and
sample each point's colour at its observations. Chosen over keeping a per-keyframe colour lookup at keyframe
creation because:

- it costs the run nothing: no image sampling on the tracking thread, no colour array in each keyframe, nothing
  more in a saved map file;
- it gives the dataset's colour even when the run itself read only the grey image (the synthetic world renders
  colour only when asked, ``dataset.color``, which a colour re-read switches on);
- a run made before the export existed (or by another map store) exports the same way.

Its cost: the dataset must still be where the run's config says (else the export has no colours, and says so),
and the re-read must give the same frames (every slamkit dataset is deterministic: files, or the synthetic world
rendered from its seed).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator, Mapping, Sequence
from typing import Any, Protocol, runtime_checkable

import cv2
import numpy as np
from numpy.typing import NDArray

from slamkit.errors import SlamkitError
from slamkit.interfaces import Dataset
from slamkit.sensors import FrameData

from .snapshot import MapSnapshot

log = logging.getLogger("slamkit.export")

U8 = NDArray[np.uint8]

#: The colour of a point none of whose observers' images could be read (and of every point without an image
#: source): mid grey, RGB.
NO_COLOUR_RGB = (128, 128, 128)


@runtime_checkable
class FrameImages(Protocol):
    """Images of the run's frames by frame index (what the exporters sample colours from)."""

    def frames(self, frame_indices: Iterable[int]) -> Iterator[tuple[int, U8]]:
        """(frame index, (H, W, 3) uint8 RGB image) for each of the given frame indices it can read, in increasing
        frame order, each once."""
        ...


def frame_rgb(data: FrameData) -> U8:
    """(H, W, 3) uint8 RGB of a frame: its colour image when the dataset has one (FrameData.color is BGR), else
    the grey image on all three channels."""
    if data.color is not None:
        return np.ascontiguousarray(data.color[:, :, ::-1])
    return np.repeat(np.asarray(data.image, np.uint8)[:, :, None], 3, axis=2)


class DatasetImages:
    """FrameImages of a Dataset: random access when it has ``__getitem__`` (every SequenceDataset), else one pass
    over it."""

    def __init__(self, dataset: Dataset) -> None:
        self.dataset = dataset

    def frames(self, frame_indices: Iterable[int]) -> Iterator[tuple[int, U8]]:
        wanted = sorted({int(i) for i in frame_indices})
        if not wanted:
            return
        getitem = getattr(self.dataset, "__getitem__", None)
        if getitem is not None:
            for i in wanted:
                try:
                    yield i, frame_rgb(getitem(i))
                except (SlamkitError, IndexError) as exc:  # a frame gone or damaged: its observations get no colour
                    log.warning("export: frame %d not read again (%s): its observations give no colour", i, exc)
            return
        pending = set(wanted)
        for data in self.dataset:
            if data.index in pending:
                pending.discard(data.index)
                yield data.index, frame_rgb(data)
                if not pending:
                    return


def dataset_for_colours(config: Mapping[str, Any]) -> Dataset:
    """The run's dataset built again from its resolved config (``config["dataset"]``) to read its colour images:
    colour switched on where the dataset has the switch (``color``), depth, stereo and IMU off where it has those.
    Errors building it (dataset moved, ...) are the dataset's own slamkit errors; a live source (``dataset=camera``)
    is not opened again (its frames now are not the run's) and is a SlamkitError."""
    from hydra.utils import get_class

    from slamkit.plugins import ComponentRegistry

    node = dict(config.get("dataset") or {})
    if "_target_" not in node:
        raise SlamkitError("the run's config has no dataset (_target_): no images to take colours from")
    try:
        live = bool(getattr(get_class(str(node["_target_"])), "live", False))
    except Exception:  # an unknown class: building it below says what is wrong
        live = False
    if live:
        raise SlamkitError("the run read a live source, whose frames were not stored")
    for key, value in (("color", True), ("depth", False), ("use_depth", False), ("imu", False)):
        if key in node:
            node[key] = value
    registry = ComponentRegistry.discover()
    dataset: Dataset = registry.instantiate("dataset", node)
    return dataset


def _sample(image: U8, uv_px: NDArray[np.float32]) -> U8:
    """(N, 3) uint8: the image's pixel nearest to each raw pixel uv_px (N, 2) (OpenCV convention), clamped to the
    image."""
    h, w = image.shape[:2]
    u = np.clip(np.rint(uv_px[:, 0]).astype(np.int64), 0, w - 1)
    v = np.clip(np.rint(uv_px[:, 1]).astype(np.int64), 0, h - 1)
    return np.asarray(image[v, u], np.uint8)


def point_colours(snapshots: Sequence[MapSnapshot], images: FrameImages | None) -> list[U8]:
    """Per snapshot, (P, 3) uint8 RGB of its points: the mean over the point's observations of the keyframe
    image's pixel at the observed feature (nearest pixel), rounded; NO_COLOUR_RGB where no observer's image was
    read (everywhere when ``images`` is None). Reads each keyframe's frame once."""
    out = [np.tile(np.array(NO_COLOUR_RGB, np.uint8), (s.n_points, 1)) for s in snapshots]
    if images is None:
        return out
    # per keyframe: which (snapshot, point row) pairs its features colour
    by_frame: dict[int, list[tuple[int, NDArray[np.float32], NDArray[np.int64]]]] = {}
    sums = [np.zeros((s.n_points, 3)) for s in snapshots]
    counts = [np.zeros(s.n_points, np.int64) for s in snapshots]
    for si, snap in enumerate(snapshots):
        row_of = {int(p): r for r, p in enumerate(snap.point_ids)}
        for kf in snap.keyframes:
            feats = np.flatnonzero(kf.point_ids >= 0)
            rows = np.array([row_of.get(int(kf.point_ids[f]), -1) for f in feats], np.int64)
            keep = rows >= 0
            by_frame.setdefault(kf.frame_index, []).append((si, kf.uv_px[feats[keep]], rows[keep]))
    for frame_index, image in images.frames(by_frame):
        rgb = np.asarray(cv2.cvtColor(image, cv2.COLOR_GRAY2RGB) if image.ndim == 2 else image, np.uint8)
        for si, uv, rows in by_frame[frame_index]:
            np.add.at(sums[si], rows, _sample(rgb, uv).astype(np.float64))
            np.add.at(counts[si], rows, 1)
    for si in range(len(snapshots)):
        seen = counts[si] > 0
        out[si][seen] = np.clip(np.rint(sums[si][seen] / counts[si][seen, None]), 0, 255).astype(np.uint8)
        if not seen.all():
            log.info("export: map %d: %d points with no colour read", snapshots[si].map_id, int((~seen).sum()))
    return out
