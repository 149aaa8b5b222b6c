"""The Python API: slamkit embedded in a program, frame by frame (docs/api.md).

``open_system(overrides)`` composes the run config from the same Hydra config groups and overrides as
``slamkit run`` (with Hydra's compose API: no command line, no working-directory change, no output directory
unless one is asked for) and builds a :class:`System`: the configured components, the Atlas and the configured
runner. Then

- ``System.track(image, timestamp_s, depth=..., right=..., imu=...)`` tracks one frame and returns a
  :class:`FrameResult` (tracking state, the frame's pose, whether it became a keyframe). It calls the runner's
  one per-frame step, the very function ``slamkit run`` calls on each frame: with ``runner=sequential`` the frames
  of a dataset fed one by one give the run's trajectory bit for bit. With ``runner=threaded`` the caller's thread
  is the tracking thread (tracking is synchronous per frame) and local mapping and loop closing run behind it.
- ``System.maps()`` / ``System.trajectory()`` read the map and the trajectory (under the maps' read locks);
  ``System.atlas`` is the Atlas itself, for reading through the MapStore protocol.
- ``System.close()`` ends the run: local mapping and loop closing finish their queues and their threads are
  joined, ``slamkit_run_finished`` fires, and the run directory is written when ``output_dir`` was given
  (the same files as ``slamkit run``). Idempotent; a System is also a context manager.
- ``System.run_dataset()`` runs the configured dataset as ``slamkit run`` does (slamkit/app.py ``run_job`` is
  this function's one-line user); the run ends with it.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from omegaconf import DictConfig, OmegaConf

from slamkit.app import Runner, build_runner
from slamkit.config import compose_config
from slamkit.errors import SlamkitError
from slamkit.frontend.stereo import StereoFrontEnd
from slamkit.geometry.se3 import invert_T
from slamkit.interfaces import Camera, Dataset, MapStore
from slamkit.map.atlas import Atlas
from slamkit.map.mapfile import MapFileInfo, save_atlas
from slamkit.pipeline.outcomes import TrackingOutcome, TrackingState
from slamkit.pipeline.trajectory import TrajectoryRecorder
from slamkit.plugins import ComponentRegistry
from slamkit.runtime.log import RunLog
from slamkit.sensors import FrameData, ImuSamples, Trajectory

log = logging.getLogger("slamkit")

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

__all__ = [
    "FrameInputError",
    "FrameResult",
    "MapData",
    "System",
    "SystemClosedError",
    "open_system",
]


class FrameInputError(SlamkitError, ValueError):
    """A frame handed to ``System.track`` that does not fit the configured camera or front end (image size or pixel
    type, a missing depth map or right image, a timestamp or frame index that does not increase). The frame is not
    tracked and the run goes on."""


class SystemClosedError(SlamkitError, RuntimeError):
    """``track`` or ``run_dataset`` on a System whose run has ended (``close()``, ``run_dataset()``, or a failure)."""


@dataclass(frozen=True)
class FrameResult:
    """What tracking did with one frame handed to ``System.track``.

    frame_index: the frame's number (0-based, increasing). timestamp_s: its time, s. state: NOT_INITIALIZED (the
    map is not initialised yet), OK (tracked) or LOST. T_w_c / T_c_w: (4, 4) float64 pose of the camera in the
    world / its inverse, as tracking estimated it on this frame (None when not tracked); the final trajectory
    (``System.trajectory()``) follows later corrections of the keyframes (local BA, loop closing).
    keyframe_made: the frame became a keyframe (or initialised a map); keyframe_ids: the ids of the keyframes made
    from it (two for the frame that initialises a monocular map: the first one is the initialisation's reference
    frame). map_id: the active map of the Atlas after the frame. n_features: keypoints extracted; inliers: map
    points matched after the last pose optimization; method: how the pose was found (e.g. "motion_model",
    "reference_keyframe", "relocalization"); message: why a frame was not tracked. outcome: the tracker's full
    record (slamkit.pipeline.outcomes.TrackingOutcome).
    """

    frame_index: int
    timestamp_s: float
    state: TrackingState
    T_w_c: F64 | None
    T_c_w: F64 | None
    keyframe_made: bool
    keyframe_ids: tuple[int, ...]
    map_id: int
    n_features: int
    inliers: int
    method: str
    message: str
    outcome: TrackingOutcome

    @property
    def tracked(self) -> bool:
        """The frame has an estimated pose (state OK)."""
        return self.state == TrackingState.OK and self.T_c_w is not None


@dataclass(frozen=True)
class MapData:
    """One map of the Atlas, copied under its read lock.

    map_id: its id in the Atlas; active: tracking and local mapping work on it. keyframe_ids: (K,) int64 in id
    order; keyframe_timestamps_s: (K,) s; T_c_w: (K, 4, 4) float64 world -> camera; T_w_c: (K, 4, 4) their
    inverses (camera centres: ``T_w_c[:, :3, 3]``, m). point_ids: (M,) int64 in id order; xyz_w: (M, 3) float64 m,
    the points' positions in the world.
    """

    map_id: int
    active: bool
    keyframe_ids: I64
    keyframe_timestamps_s: F64
    T_c_w: F64
    T_w_c: F64
    point_ids: I64
    xyz_w: F64

    @property
    def n_keyframes(self) -> int:
        return int(self.keyframe_ids.shape[0])

    @property
    def n_points(self) -> int:
        return int(self.point_ids.shape[0])

    @classmethod
    def of_store(cls, store: MapStore, map_id: int, active: bool) -> MapData:
        """Copy a map's keyframes and points through the MapStore protocol, under its read lock."""
        with store.read():
            kfs = [store.get_keyframe(k) for k in sorted(store.keyframe_ids())]
            point_ids = np.array(sorted(store.point_ids()), dtype=np.int64)
            xyz_w = store.point_rows(point_ids, "xyz_w") if point_ids.size else np.zeros((0, 3))
            return cls(
                map_id=map_id,
                active=active,
                keyframe_ids=np.array([kf.id for kf in kfs], dtype=np.int64),
                keyframe_timestamps_s=np.array([kf.timestamp_s for kf in kfs], dtype=np.float64),
                T_c_w=np.stack([kf.T_c_w for kf in kfs]) if kfs else np.zeros((0, 4, 4)),
                T_w_c=np.stack([kf.T_w_c for kf in kfs]) if kfs else np.zeros((0, 4, 4)),
                point_ids=point_ids,
                xyz_w=np.array(xyz_w, dtype=np.float64).reshape(-1, 3),
            )


def open_system(
    overrides: Sequence[str] | None = None,
    config_dir: str | Path | None = None,
    *,
    output_dir: str | Path | None = None,
    registry: ComponentRegistry | None = None,
) -> System:
    """Compose the config as ``slamkit run OVERRIDES...`` would and build a :class:`System` from it.

    overrides: Hydra overrides, exactly as on the command line (``["dataset=tum_rgbd", "dataset.root=...",
    "runner=sequential", "+backend=gtsam"]``). config_dir: a folder of config groups of your own (e.g.
    ``DIR/dataset/mycam.yaml``, then ``dataset=mycam``), added to Hydra's config search path
    (``hydra.searchpath``). output_dir: where ``close()`` writes the run directory (trajectory.tum, keyframes.tum,
    metrics.json, ...); None writes nothing. registry: the plugins' components (default: discovered from the
    installed entry points). Raises Hydra's errors for an unknown key or option and a SlamkitError for a bad value
    (ConfigError, DatasetError, ...)."""
    args = list(overrides or [])
    if config_dir is not None:
        folder = Path(config_dir).expanduser().resolve()
        if not folder.is_dir():
            raise FileNotFoundError(f"open_system: config_dir {folder} is not a folder")
        args.append(f"hydra.searchpath=[file://{folder}]")
    registry = registry or ComponentRegistry.discover()
    return System(compose_config(args, registry), output_dir=output_dir, registry=registry)


class System:
    """A SLAM system built from a composed config: feed it frames with ``track``, read its maps, ``close`` it.

    cfg: a run config (``slamkit.config.compose_config`` or ``slamkit run``'s); the build fills in what the dataset
    decides (its camera's ORB settings) in place. output_dir: where the run directory is written when the run ends
    (None: nowhere). The configured dataset gives the camera (its calibration) and the ground truth ``metrics.json``
    is computed against; its frames are read only by ``run_dataset`` (or by you: ``system.dataset``).
    """

    def __init__(
        self, cfg: DictConfig, *, output_dir: str | Path | None = None, registry: ComponentRegistry | None = None
    ) -> None:
        runner, dataset = build_runner(cfg, registry)
        config = OmegaConf.to_container(cfg, resolve=True)
        assert isinstance(config, dict)
        self.cfg = cfg
        self.config: dict[str, Any] = {str(k): v for k, v in config.items()}
        self.runner: Runner = runner
        self.dataset: Dataset = dataset
        self.camera: Camera = dataset.camera
        self.output_dir = None if output_dir is None else Path(output_dir)
        frontend = runner.tracker.frontend
        self._needs_depth = bool(getattr(frontend, "uses_depth", False))
        self._needs_right = bool(getattr(frontend, "uses_right", isinstance(frontend, StereoFrontEnd)))
        right = getattr(dataset, "camera_right", None)
        self._camera_right: Camera = right if right is not None else self.camera
        self._started = False
        self._ended: str | None = None  # why the run ended (None: it has not)
        self._last_index: int | None = None
        self._last_timestamp_s: float | None = None

    # ---- the run ----------------------------------------------------------------------------------

    def track(
        self,
        image: NDArray[np.uint8],
        timestamp_s: float,
        *,
        depth: NDArray[np.floating[Any]] | None = None,
        right: NDArray[np.uint8] | None = None,
        imu: ImuSamples | None = None,
        frame_index: int | None = None,
    ) -> FrameResult:
        """Track one frame and return what tracking did with it.

        image: (H, W) uint8 grey, or (H, W, 3) uint8 BGR (converted to grey as the dataset readers do, and kept as
        the frame's colour), H x W the configured camera's. timestamp_s: capture time, s, increasing. depth:
        (H, W) float depth along the optical axis, m, registered to the image (0 or NaN: unknown) — required by
        an RGB-D front end (``frontend=rgbd``). right: the rectified right image of a stereo pair, as ``image`` —
        required by ``frontend=stereo``. imu: IMU samples with t in (previous frame's time, this frame's time].
        frame_index: the frame's number (default: the previous one + 1, from 0; a gap is a dropped frame).

        Raises FrameInputError for a frame that does not fit (not tracked; the run goes on), SystemClosedError
        after the run ended. An exception from the pipeline itself ends the run (as it ends ``slamkit run``: the
        run directory is written) and is raised.
        """
        self._check_open("track")
        data = self._frame(image, timestamp_s, depth, right, imu, frame_index)
        if not self._started:
            self._begin()
        try:
            out = self.runner.step(data, self.camera)
        except BaseException as exc:
            self._end(exc)
            raise
        self._last_index, self._last_timestamp_s = data.index, data.timestamp_s
        return _frame_result(out, self.runner.atlas.active_id)

    def run_dataset(self) -> RunLog:
        """Run the configured dataset through the configured runner, as ``slamkit run`` does (frames the dataset
        cannot read are skipped or stop the run, ``runner.bad_frames``; the threaded runner plays it from its own
        thread), write the run directory when ``output_dir`` was given, and end the run. Only on a System that has
        tracked nothing yet. Returns the run's log; raises what ended the run when it failed."""
        self._check_open("run_dataset")
        if self._started:
            raise SystemClosedError(
                "System.run_dataset: frames were tracked already; open a new system to run a dataset"
            )
        self._started = True
        try:
            return self.runner.run(self.dataset, self.camera, run_dir=self.output_dir, config=self.config)
        except BaseException as exc:
            self._ended = f"the run failed: {type(exc).__name__}: {exc}"
            raise
        finally:
            if self._ended is None:
                self._ended = "run_dataset() ended the run"

    def close(self) -> None:
        """End the run: local mapping and loop closing finish their queues and their threads are joined,
        ``slamkit_run_finished`` fires and the run directory is written when ``output_dir`` was given. Calling it
        again does nothing. Raises what failed in a pipeline thread (PipelineThreadError)."""
        if self._ended is not None:
            return
        if not self._started:
            self._begin()
        self._end(None)

    def __enter__(self) -> System:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._ended is not None:
            return
        if exc is None:
            self.close()
            return
        if not self._started:
            self._begin()
        self._end(exc)  # the block failed: the run did too (stopped at once; the run directory says so)

    @property
    def closed(self) -> bool:
        """Whether the run has ended (``track`` raises SystemClosedError)."""
        return self._ended is not None

    # ---- reading the map --------------------------------------------------------------------------

    @property
    def atlas(self) -> Atlas:
        """The Atlas of maps (``atlas.active``, ``atlas.items()``: each a MapStore). With the threaded runner local
        mapping and loop closing change the maps while you read: take the map's ``read()`` lock."""
        return self.runner.atlas

    @property
    def log(self) -> RunLog:
        """What the run did so far, frame by frame and keyframe by keyframe."""
        return self.runner.log

    def maps(self) -> list[MapData]:
        """Every map of the Atlas (keyframes and points), each copied under its read lock, in map id order."""
        active = self.atlas.active_id
        return [MapData.of_store(store, map_id, map_id == active) for map_id, store in self.atlas.items()]

    def trajectory(self) -> Trajectory:
        """(N,) timestamps and (N, 4, 4) T_w_c of every frame tracked in the active map, each placed relative to its
        reference keyframe as that keyframe is now (ORB-SLAM's trajectory: it follows local BA and loop corrections;
        ``slamkit run`` writes the same as trajectory.tum)."""
        store = self.atlas.active
        with store.read():
            return self.runner.recorder.frames(store)

    def keyframe_trajectory(self) -> Trajectory:
        """The active map's keyframes: (K,) timestamps and (K, 4, 4) T_w_c in time order (keyframes.tum)."""
        store = self.atlas.active
        with store.read():
            return TrajectoryRecorder.keyframes(store)

    def save_map(self, path: str | os.PathLike[str]) -> MapFileInfo:
        """Write every map of the Atlas to ``path`` (slamkit's map file: docs/atlas.md, "Saved maps"), atomically,
        with this run's config; ``slamkit run map.load=PATH`` (or ``open_system(["map.load=PATH"])``) reads it back.
        Works during the run (each map is read under its read lock) and after ``close``. Returns what was written;
        MapFileError naming the file when it cannot be written. The file keeps every map's frames too (this run's
        and the earlier sessions' of a loaded map), for a later session's trajectory."""
        return save_atlas(self.atlas, path, self.config, self.runner.map_frames())

    # ---- internals --------------------------------------------------------------------------------

    def _check_open(self, what: str) -> None:
        if self._ended is not None:
            raise SystemClosedError(f"System.{what}: the run has ended ({self._ended}); open a new system")

    def _begin(self) -> None:
        self._started = True
        try:
            self.runner.begin(self.dataset, self.camera, self.output_dir, self.config)
        except BaseException as exc:
            self._ended = f"it failed to start: {type(exc).__name__}: {exc}"
            raise

    def _end(self, ended_by: BaseException | None) -> None:
        self._ended = "close() ended it" if ended_by is None else f"it failed: {type(ended_by).__name__}: {ended_by}"
        self.runner.end(ended_by)

    def _frame(
        self,
        image: Any,
        timestamp_s: float,
        depth: Any,
        right: Any,
        imu: ImuSamples | None,
        frame_index: int | None,
    ) -> FrameData:
        """Check one frame against the configured camera and front end and build its FrameData."""
        grey, color = _grey_image("image", image, self.camera)
        t = float(timestamp_s)
        if not np.isfinite(t):
            raise FrameInputError(f"System.track: timestamp_s = {timestamp_s!r}; expected a finite time in seconds")
        if self._last_timestamp_s is not None and not t > self._last_timestamp_s:
            raise FrameInputError(
                f"System.track: timestamp_s = {t!r} s does not increase (the previous frame's: {self._last_timestamp_s!r} s)"
            )
        index = (0 if self._last_index is None else self._last_index + 1) if frame_index is None else int(frame_index)
        if index < 0 or (self._last_index is not None and index <= self._last_index):
            raise FrameInputError(
                f"System.track: frame_index = {index}; expected a number >= 0 above the previous frame's "
                f"({self._last_index})"
            )
        depth_m = None
        if depth is not None:
            depth_m = _depth_map(depth, grey.shape)
        elif self._needs_depth:
            raise FrameInputError(
                "System.track: the configured front end (frontend=rgbd) needs a depth map: pass depth=(H, W) float32 "
                "metres registered to the image"
            )
        image_right = None
        if right is not None:
            image_right, _ = _grey_image("right", right, self._camera_right)
        elif self._needs_right:
            raise FrameInputError(
                "System.track: the configured front end (frontend=stereo) needs the right image: pass right=(H, W) "
                "uint8, rectified"
            )
        if imu is not None and not isinstance(imu, ImuSamples):
            raise FrameInputError(
                f"System.track: imu is a {type(imu).__name__}; expected slamkit.sensors.ImuSamples(t_s, acc_mps2, "
                "gyro_radps)"
            )
        return FrameData(
            index=index,
            timestamp_s=t,
            image=grey,
            color=color,
            depth_m=depth_m,
            image_right=image_right,
            imu=imu if imu is not None else ImuSamples.empty(),
        )


def _grey_image(name: str, image: Any, camera: Camera) -> tuple[NDArray[np.uint8], NDArray[np.uint8] | None]:
    """(H, W) uint8 grey image (and the (H, W, 3) BGR colour one when given one) of the camera's size, or
    FrameInputError naming what is wrong."""
    if not isinstance(image, np.ndarray):
        raise FrameInputError(f"System.track: {name} is a {type(image).__name__}; expected a numpy array")
    expected = f"({camera.height}, {camera.width}) uint8 grey or ({camera.height}, {camera.width}, 3) uint8 BGR"
    if image.dtype != np.uint8:
        raise FrameInputError(f"System.track: {name} has pixel type {image.dtype}; expected {expected}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if (
        image.shape[:2] != (camera.height, camera.width)
        or image.ndim not in (2, 3)
        or (image.ndim == 3 and image.shape[2] != 3)
    ):
        raise FrameInputError(
            f"System.track: {name} of shape {image.shape}; expected {expected} (the configured camera's size)"
        )
    if image.ndim == 2:
        return image, None
    color = np.ascontiguousarray(image)
    return np.asarray(cv2.cvtColor(color, cv2.COLOR_BGR2GRAY), dtype=np.uint8), color


def _depth_map(depth: Any, shape: tuple[int, ...]) -> NDArray[np.float32]:
    """(H, W) float32 depth in metres of the image's size, or FrameInputError."""
    if not isinstance(depth, np.ndarray) or not np.issubdtype(depth.dtype, np.floating):
        kind = depth.dtype if isinstance(depth, np.ndarray) else type(depth).__name__
        raise FrameInputError(
            f"System.track: depth is {kind}; expected a float32 array of metres (convert a 16-bit depth image: "
            "depth_png / scale, TUM RGB-D's scale is 5000)"
        )
    if depth.shape != tuple(shape[:2]):
        raise FrameInputError(
            f"System.track: depth of shape {depth.shape}; expected {tuple(shape[:2])}, registered to the image"
        )
    return depth if depth.dtype == np.float32 else depth.astype(np.float32)


def _frame_result(out: TrackingOutcome, map_id: int) -> FrameResult:
    T_c_w = None if out.T_c_w is None else out.T_c_w.copy()
    return FrameResult(
        frame_index=out.frame_index,
        timestamp_s=out.timestamp_s,
        state=out.state,
        T_w_c=None if T_c_w is None else invert_T(T_c_w),
        T_c_w=T_c_w,
        keyframe_made=bool(out.keyframe_ids),
        keyframe_ids=out.keyframe_ids,
        map_id=map_id,
        n_features=out.n_features,
        inliers=out.inliers,
        method=out.method,
        message=out.message,
        outcome=out,
    )
