"""One run streamed to rerun: the camera with its image and tracked features, the trajectory, keyframes, map
points coloured by age, loop closures and merges on the timeline.

Entity paths (world frame = the map's frame, metres; camera axes right-down-forward as slamkit's):
- ``world/camera`` the current camera (Transform3D T_w_c, Pinhole), ``world/camera/image`` its image (JPEG) and
  ``world/camera/image/features`` its keypoints (green: matched to a map point, red: not);
- ``world/trajectory`` the tracked camera centres so far (a line strip, re-logged at each keyframe and at the end);
- ``world/map_<id>/keyframes`` keyframe centres (labels: keyframe ids) and ``world/map_<id>/points`` map points,
  coloured by age (old blue, new yellow); the final map at the end of the run;
- ``world/loops/<n>`` a line between the two keyframes of each closed loop; ``events`` a text log of initialisations,
  lost tracking, loops and merges; ``plots/*`` tracking time and inliers per frame.
Timelines: ``frame`` (the frame index) and ``time`` (the frame's timestamp, s).
"""

from __future__ import annotations

import logging
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from slamkit.events import (
    FrameTracked,
    KeyFrameCulled,
    KeyFrameInserted,
    LoopClosed,
    MapCreated,
    MapsMerged,
    RunFinished,
    RunStarted,
)
from slamkit_rerun.settings import ViewerSettings

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

TRACKED_RGB = (40, 200, 60)
UNTRACKED_RGB = (220, 50, 40)
KEYFRAME_RGB = (80, 140, 255)
TRAJECTORY_RGB = (255, 255, 255)
LOOP_RGB = (255, 0, 255)
PLOT_BATCH_FRAMES = 30  # per-frame plots are sent in columns of this many frames (and at the end)


def age_colours(point_ids: NDArray[np.int64]) -> NDArray[np.uint8]:
    """(P,) point ids (monotonic: a larger id is a younger point) -> (P, 3) uint8 colours, oldest blue to youngest
    yellow, by rank."""
    n = point_ids.shape[0]
    if n == 0:
        return np.zeros((0, 3), np.uint8)
    if n == 1 or bool(np.all(point_ids[1:] > point_ids[:-1])):
        rank = np.linspace(0.0, 1.0, n)  # already in id order (PointCloud.points): no sort
    else:
        rank = np.empty(n, np.float64)
        rank[np.argsort(point_ids, kind="stable")] = np.linspace(0.0, 1.0, n)
    blue, yellow = np.array([40.0, 90.0, 255.0]), np.array([255.0, 220.0, 40.0])
    return (blue + rank[:, None] * (yellow - blue)).astype(np.uint8)


class PointCloud:
    """Map points by id, as the latest event gave them: arrays indexed by point id (ids are small monotonic
    integers), so updating M points and reading all P back are array operations, not per-point Python."""

    def __init__(self) -> None:
        self._xyz = np.zeros((0, 3), np.float64)
        self._known = np.zeros(0, np.bool_)

    def __len__(self) -> int:
        return int(np.count_nonzero(self._known))

    def update(self, point_ids: NDArray[np.int64], points_w: F64) -> None:
        """Set the positions (M, 3) m of points (M,) ids (new or known)."""
        if point_ids.size == 0:
            return
        need = int(point_ids.max()) + 1
        if need > self._known.shape[0]:
            size = max(need, 2 * self._known.shape[0], 1024)
            xyz = np.zeros((size, 3), np.float64)
            known = np.zeros(size, np.bool_)
            xyz[: self._xyz.shape[0]] = self._xyz
            known[: self._known.shape[0]] = self._known
            self._xyz, self._known = xyz, known
        self._xyz[point_ids] = points_w
        self._known[point_ids] = True

    def points(self) -> tuple[NDArray[np.int64], F64]:
        """(P,) ids in increasing order and their (P, 3) positions."""
        ids = np.flatnonzero(self._known).astype(np.int64)
        return ids, self._xyz[ids]


def camera_centre(T_c_w: F64) -> F64:
    """(4, 4) T_c_w -> (3,) the camera centre in the world frame, m."""
    R, t = T_c_w[:3, :3], T_c_w[:3, 3]
    return np.asarray(-R.T @ t, dtype=np.float64)


class RerunViewer:
    """Logs one run's events to a rerun recording (the plugin makes one per run).

    rr: the ``rerun`` module (imported by the plugin only when a run asks for the viewer)."""

    def __init__(self, rr: Any, settings: ViewerSettings, started: RunStarted) -> None:
        self.rr = rr
        self.settings = settings
        self.rec = rr.RecordingStream("slamkit", recording_id=f"slamkit-run-{started.run_id}")
        if settings.save is not None:
            settings.save.parent.mkdir(parents=True, exist_ok=True)
            self.rec.save(str(settings.save))
        elif settings.connect is not None:
            self.rec.connect_grpc(settings.connect)
        else:
            self.rec.spawn()
        self._centres: list[F64] = []  # tracked camera centres, in frame order
        self._keyframes: dict[int, dict[int, F64]] = {}  # map id -> keyframe id -> centre
        self._points: dict[int, PointCloud] = {}  # map id -> its points as local mapping left them
        self._plots: dict[str, list[float]] = {"frame": [], "time": [], "track_ms": [], "inliers": []}
        self._loops = 0
        self._frame_index = -1
        rec = self.rec
        rec.log("world", rr.ViewCoordinates.RDF, static=True)  # slamkit's camera axes: x right, y down, z forward
        if started.K is not None and started.image_size is not None:
            rec.log(
                "world/camera/image",
                rr.Pinhole(image_from_camera=started.K, resolution=list(started.image_size)),
                static=True,
            )
        frames = "a live stream of" if started.n_frames is None else started.n_frames
        rec.log(
            "events",
            rr.TextLog(f"run started: {started.dataset}, {frames} frames, {started.runner} runner"),
            static=True,
        )

    # ---- the timeline --------------------------------------------------------------------------------

    def _at_frame(self, frame_index: int, timestamp_s: float | None = None) -> None:
        self.rec.set_time("frame", sequence=int(frame_index))
        if timestamp_s is not None:
            self.rec.set_time("time", duration=float(timestamp_s))

    def _at_last_frame(self) -> None:
        """Events of local mapping and loop closing carry no frame: they are placed at the last frame tracked."""
        self.rec.set_time("frame", sequence=max(self._frame_index, 0))

    # ---- events --------------------------------------------------------------------------------------

    def frame_tracked(self, event: FrameTracked, stale: bool = False) -> None:
        """The frame's pose, trajectory point and plots; its image and features unless ``stale`` (newer frames are
        waiting: a live view skips to the latest image)."""
        rr, rec = self.rr, self.rec
        self._frame_index = event.frame_index
        self._at_frame(event.frame_index, event.timestamp_s)
        plots = self._plots
        plots["frame"].append(event.frame_index)
        plots["time"].append(event.timestamp_s)
        plots["track_ms"].append(float(event.timings_ms.get("track_ms", np.nan)))
        plots["inliers"].append(float(event.inliers))
        if len(plots["frame"]) >= PLOT_BATCH_FRAMES:
            self._send_plots()
        if event.T_c_w is not None:
            T_w_c = np.linalg.inv(event.T_c_w)
            rec.log("world/camera", rr.Transform3D(translation=T_w_c[:3, 3], mat3x3=T_w_c[:3, :3]))
            self._centres.append(np.array(T_w_c[:3, 3], dtype=np.float64))
        elif event.state == "lost":
            rec.log("events", rr.TextLog(f"frame {event.frame_index}: lost ({event.message})", level="WARN"))
        if stale:
            return
        if event.image is not None and event.frame_index % self.settings.image_every == 0:
            ok, jpeg = cv2.imencode(".jpg", event.image, [cv2.IMWRITE_JPEG_QUALITY, self.settings.jpeg_quality])
            if ok:
                # the encoded bytes as a uint8 array: rerun 0.41 turns a ``bytes`` object into its blob element by
                # element in Python (13 ms for a 100 kB JPEG, measured) and an array in one copy (1 ms)
                rec.log("world/camera/image", rr.EncodedImage(contents=jpeg.reshape(-1), media_type="image/jpeg"))
        if event.uv_px is not None and event.tracked is not None:
            colours = np.where(event.tracked[:, None], TRACKED_RGB, UNTRACKED_RGB).astype(np.uint8)
            rec.log("world/camera/image/features", rr.Points2D(event.uv_px, colors=colours, radii=2.0))

    def map_created(self, event: MapCreated) -> None:
        self._at_frame(event.frame_index, event.timestamp_s)
        self.rec.log(
            "events",
            self.rr.TextLog(f"map {event.map_id} initialised at frame {event.frame_index}: {event.n_points} points"),
        )

    def keyframe_inserted(self, event: KeyFrameInserted) -> None:
        if event.T_c_w is None or event.point_ids is None or event.points_w is None:
            return
        self._at_last_frame()
        keyframes = self._keyframes.setdefault(event.map_id, {})
        keyframes[event.kf_id] = camera_centre(event.T_c_w)
        self._points.setdefault(event.map_id, PointCloud()).update(event.point_ids, event.points_w)
        self._log_map(event.map_id)
        self._log_trajectory()

    def keyframe_culled(self, event: KeyFrameCulled) -> None:
        self._keyframes.get(event.map_id, {}).pop(event.kf_id, None)

    def loop_closed(self, event: LoopClosed) -> None:
        self._at_last_frame()
        keyframes = self._keyframes.get(event.map_id, {})
        self.rec.log(
            "events",
            self.rr.TextLog(
                f"loop closed: keyframe {event.kf_id} <-> {event.loop_kf_id} ({event.matches} matches, "
                f"scale {event.scale:.3f})"
            ),
        )
        if event.kf_id in keyframes and event.loop_kf_id in keyframes:
            strip = np.stack([keyframes[event.kf_id], keyframes[event.loop_kf_id]])
            self.rec.log(f"world/loops/{self._loops}", self.rr.LineStrips3D([strip], colors=[LOOP_RGB]))
        self._loops += 1

    def maps_merged(self, event: MapsMerged) -> None:
        self._at_last_frame()
        self.rec.log(
            "events",
            self.rr.TextLog(
                f"map {event.merged_map_id} merged into map {event.into_map_id} "
                f"(keyframe {event.kf_id} matched {event.matched_kf_id})"
            ),
        )

    def run_finished(self, event: RunFinished, frames_skipped: int = 0) -> None:
        """The final maps (every keyframe at its final pose, every point), then the recording is closed.
        frames_skipped: frames whose image and features were not drawn (stale), said in the event log."""
        self._at_last_frame()
        for snapshot in event.maps:
            self._keyframes[snapshot.map_id] = {
                int(k): T_w_c[:3, 3].copy() for k, T_w_c in zip(snapshot.keyframe_ids, snapshot.T_w_c, strict=True)
            }
            final = PointCloud()
            final.update(snapshot.point_ids, snapshot.points_w)
            self._points[snapshot.map_id] = final
            self._log_map(snapshot.map_id)
        self._log_trajectory()
        self._send_plots()
        if frames_skipped:
            self.rec.log("events", self.rr.TextLog(f"{frames_skipped} frame images skipped to keep up with tracking"))
        level = "INFO" if event.status == "ok" else "ERROR"
        self.rec.log(
            "events", self.rr.TextLog(f"run {event.status}" + (f": {event.error}" if event.error else ""), level=level)
        )
        self.close()

    def close(self) -> None:
        """Flush and close the recording (the .rrd file is complete after this)."""
        self.rec.flush()
        self.rec.disconnect()

    # ---- drawing -------------------------------------------------------------------------------------

    def _log_map(self, map_id: int) -> None:
        rr = self.rr
        keyframes = self._keyframes.get(map_id, {})
        if keyframes:
            kf_ids = sorted(keyframes)
            self.rec.log(
                f"world/map_{map_id}/keyframes",
                rr.Points3D(
                    np.stack([keyframes[k] for k in kf_ids]),
                    colors=[KEYFRAME_RGB],
                    radii=0.03,
                    labels=[str(k) for k in kf_ids],
                    show_labels=False,
                ),
            )
        cloud = self._points.get(map_id)
        if cloud is not None and len(cloud):
            ids, xyz = cloud.points()
            self.rec.log(f"world/map_{map_id}/points", rr.Points3D(xyz, colors=age_colours(ids), radii=0.01))

    def _send_plots(self) -> None:
        """The buffered per-frame plots in one columnar send (a log call per value costs ~0.5 ms of Python)."""
        plots = self._plots
        if not plots["frame"]:
            return
        rr = self.rr
        indexes = [
            rr.TimeColumn("frame", sequence=np.asarray(plots["frame"], np.int64)),
            rr.TimeColumn("time", duration=np.asarray(plots["time"], np.float64)),
        ]
        for name in ("track_ms", "inliers"):
            self.rec.send_columns(f"plots/{name}", indexes=indexes, columns=rr.Scalars.columns(scalars=plots[name]))
        for values in plots.values():
            values.clear()

    def _log_trajectory(self) -> None:
        if len(self._centres) >= 2:
            self.rec.log("world/trajectory", self.rr.LineStrips3D([np.stack(self._centres)], colors=[TRAJECTORY_RGB]))
