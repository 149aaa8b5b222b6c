"""COLMAP text model of a map: cameras.txt, images.txt, points3D.txt (COLMAP's documented "Output Format", text
variant), which COLMAP, pycolmap and the Gaussian-splatting / NeRF tools that read COLMAP models load.

- cameras.txt: ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]``, one camera per distinct calibration, ids from 1. A pinhole
  camera without distortion is ``PINHOLE fx fy cx cy``; with radial-tangential distortion ``OPENCV fx fy cx cy k1 k2
  p1 p2``, or ``FULL_OPENCV fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6`` (k4..k6 = 0) when k3 is not 0; Kannala-Brandt is
  ``OPENCV_FISHEYE fx fy cx cy k1 k2 k3 k4``. The models' equations are the same as slamkit's (OpenCV's).
- images.txt: per keyframe ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` (the keyframe id; T_c_w, world ->
  camera, as COLMAP's quaternion and translation) then ``X Y POINT3D_ID`` for every feature of the keyframe (the
  point it observes, -1 for none).
- points3D.txt: ``POINT3D_ID X Y Z R G B ERROR TRACK[]`` (the map point id; colour as in the PLY export; ERROR the
  mean reprojection error of the track, px, -1 when no observation projects; TRACK ``IMAGE_ID POINT2D_IDX`` pairs:
  the point's observations).

Pixel convention. COLMAP puts the centre of the top-left pixel at (0.5, 0.5); OpenCV, ORB-SLAM and slamkit at
(0, 0). The principal points and the 2D points are written shifted by +0.5 px, so the model projects a point where
COLMAP expects its feature; reprojection errors are the same in both conventions.

Image names are ``frame_NNNNNN.png`` (the keyframe's frame index, 6 digits); with an image folder the keyframes'
images are written there under those names (what a splatting pipeline reads beside the model).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from slamkit.errors import ExportError
from slamkit.geometry.so3 import matrix_to_quat_xyzw
from slamkit.interfaces import Camera

from .colours import FrameImages
from .files import atomic_write_bytes, atomic_write_text
from .snapshot import KeyFrameRecord, MapSnapshot

#: COLMAP's pixel centre (0.5, 0.5) minus OpenCV's (0, 0), px (see the module docstring).
COLMAP_PIXEL_OFFSET_PX = 0.5


def image_name(frame_index: int) -> str:
    """The COLMAP image name of the keyframe made from frame ``frame_index``."""
    return f"frame_{frame_index:06d}.png"


def _num(v: float) -> str:
    # repr: the shortest text that reads back to the same float64 (poses and points round-trip exactly)
    return repr(float(v))


def colmap_camera(camera: Camera) -> tuple[str, list[float]]:
    """(COLMAP model name, params) of a slamkit camera, principal point in COLMAP's pixel convention."""
    fx, fy = float(camera.K[0, 0]), float(camera.K[1, 1])
    cx, cy = float(camera.K[0, 2]) + COLMAP_PIXEL_OFFSET_PX, float(camera.K[1, 2]) + COLMAP_PIXEL_OFFSET_PX
    dist = [float(d) for d in np.asarray(camera.dist, np.float64).ravel()]
    if camera.model == "kannala_brandt":
        return "OPENCV_FISHEYE", [fx, fy, cx, cy, *dist[:4]]
    if camera.model != "pinhole":
        raise ExportError(f"camera model {camera.model!r}: no COLMAP equivalent known (pinhole, kannala_brandt)")
    k1, k2, p1, p2, k3 = (dist + [0.0] * 5)[:5]
    if k3 != 0.0:
        return "FULL_OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]
    if any(d != 0.0 for d in (k1, k2, p1, p2)):
        return "OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2]
    return "PINHOLE", [fx, fy, cx, cy]


def _observed_points(snap: MapSnapshot) -> dict[int, NDArray[np.int64]]:
    """keyframe id -> (N,) int64, per feature the exported point it observes (from the points' tracks, so that
    images.txt and points3D.txt agree), -1 for none."""
    out = {kf.id: np.full(kf.uv_px.shape[0], -1, np.int64) for kf in snap.keyframes}
    for pid, track in zip(snap.point_ids.tolist(), snap.tracks, strict=True):
        for kf_id, feat in track:
            if kf_id in out and 0 <= feat < out[kf_id].shape[0]:
                out[kf_id][feat] = pid
    return out


def reprojection_errors(snap: MapSnapshot) -> NDArray[np.float64]:
    """(P,) px: per point, the mean distance between its observations' pixels and its projection through each
    observing keyframe's camera (raw image); -1 where no observation projects (behind the camera)."""
    kf_of = {kf.id: kf for kf in snap.keyframes}
    sums = np.zeros(snap.n_points)
    counts = np.zeros(snap.n_points, np.int64)
    per_kf: dict[int, tuple[list[int], list[int]]] = {}
    for row, track in enumerate(snap.tracks):
        for kf_id, feat in track:
            if kf_id in kf_of:
                rows, feats = per_kf.setdefault(kf_id, ([], []))
                rows.append(row)
                feats.append(feat)
    for kf_id, (rows, feats) in per_kf.items():
        kf = kf_of[kf_id]
        r = np.array(rows, np.int64)
        xyz_c = snap.xyz_w[r] @ kf.T_c_w[:3, :3].T + kf.T_c_w[:3, 3]
        with np.errstate(invalid="ignore", divide="ignore"):
            uv = np.asarray(kf.camera.project(xyz_c), np.float64).reshape(-1, 2)
        err = np.linalg.norm(uv - kf.uv_px[np.array(feats, np.int64)].astype(np.float64), axis=1)
        ok = (xyz_c[:, 2] > 0) & np.isfinite(err)
        np.add.at(sums, r[ok], err[ok])
        np.add.at(counts, r[ok], 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, sums / np.maximum(counts, 1), -1.0)


def _images_text(snap: MapSnapshot, camera_ids: dict[int, int], observed: dict[int, NDArray[np.int64]]) -> str:
    n_obs = sum(int((o >= 0).sum()) for o in observed.values())
    mean_obs = n_obs / len(snap.keyframes) if snap.keyframes else 0.0
    lines = [
        "# Image list with two lines of data per image:",
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
        "#   POINTS2D[] as (X, Y, POINT3D_ID)",
        f"# Number of images: {len(snap.keyframes)}, mean observations per image: {mean_obs}",
    ]
    for kf in snap.keyframes:
        qx, qy, qz, qw = matrix_to_quat_xyzw(kf.T_c_w[:3, :3])
        t = kf.T_c_w[:3, 3]
        head = [str(kf.id), *(_num(v) for v in (qw, qx, qy, qz, *t)), str(camera_ids[kf.id])]
        lines.append(" ".join([*head, image_name(kf.frame_index)]))
        uv = kf.uv_px.astype(np.float64) + COLMAP_PIXEL_OFFSET_PX
        lines.append(
            " ".join(f"{_num(u)} {_num(v)} {int(p)}" for (u, v), p in zip(uv, observed[kf.id].tolist(), strict=True))
        )
    return "\n".join(lines) + "\n"


def _points_text(snap: MapSnapshot, rgb: NDArray[np.uint8], errors: NDArray[np.float64]) -> str:
    track_len = sum(len(t) for t in snap.tracks) / snap.n_points if snap.n_points else 0.0
    lines = [
        "# 3D point list with one line of data per point:",
        "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
        f"# Number of points: {snap.n_points}, mean track length: {track_len}",
    ]
    kf_ids = {kf.id for kf in snap.keyframes}
    for row, pid in enumerate(snap.point_ids.tolist()):
        x, y, z = snap.xyz_w[row]
        r, g, b = (int(c) for c in rgb[row])
        track = " ".join(f"{k} {f}" for k, f in snap.tracks[row] if k in kf_ids)
        lines.append(f"{pid} {_num(x)} {_num(y)} {_num(z)} {r} {g} {b} {_num(errors[row])} {track}".rstrip())
    return "\n".join(lines) + "\n"


def _cameras(keyframes: Sequence[KeyFrameRecord]) -> tuple[str, dict[int, int]]:
    """cameras.txt and keyframe id -> camera id (one camera per distinct model and parameters, ids from 1)."""
    ids: dict[tuple[str, int, int, tuple[float, ...]], int] = {}
    of_kf: dict[int, int] = {}
    for kf in keyframes:
        model, params = colmap_camera(kf.camera)
        key = (model, int(kf.camera.width), int(kf.camera.height), tuple(params))
        of_kf[kf.id] = ids.setdefault(key, len(ids) + 1)
    lines = [
        "# Camera list with one line of data per camera:",
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
        f"# Number of cameras: {len(ids)}",
    ]
    for (model, width, height, values), cam_id in ids.items():
        lines.append(" ".join([str(cam_id), model, str(width), str(height), *(_num(v) for v in values)]))
    return "\n".join(lines) + "\n", of_kf


def write_colmap_model(out_dir: Path, snap: MapSnapshot, rgb: NDArray[np.uint8]) -> Path:
    """cameras.txt, images.txt and points3D.txt of one map in ``out_dir`` (created). rgb: (P, 3) uint8 point
    colours. Returns out_dir."""
    if not all(math.isfinite(float(v)) for kf in snap.keyframes for v in kf.T_c_w.ravel()):
        raise ExportError(f"{out_dir}: map {snap.map_id} has a keyframe with a non-finite pose; not written")
    cameras_text, camera_ids = _cameras(snap.keyframes)
    observed = _observed_points(snap)
    atomic_write_text(out_dir / "cameras.txt", cameras_text)
    atomic_write_text(out_dir / "images.txt", _images_text(snap, camera_ids, observed))
    atomic_write_text(out_dir / "points3D.txt", _points_text(snap, rgb, reprojection_errors(snap)))
    return out_dir


def write_keyframe_images(images_dir: Path, snapshots: Sequence[MapSnapshot], images: FrameImages) -> int:
    """Write each keyframe's image (PNG, lossless) as ``images_dir/<image_name>``; returns how many were written."""
    wanted = {kf.frame_index for snap in snapshots for kf in snap.keyframes}
    n = 0
    for frame_index, rgb in images.frames(wanted):
        ok, png = cv2.imencode(".png", np.ascontiguousarray(rgb[:, :, ::-1]))
        if not ok:
            raise ExportError(f"{images_dir / image_name(frame_index)}: the image could not be encoded as PNG")
        atomic_write_bytes(images_dir / image_name(frame_index), png.tobytes())
        n += 1
    return n
