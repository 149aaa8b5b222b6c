"""Reader of ORB-SLAM2 / ORB-SLAM3 settings files (``%YAML:1.0``, read with cv2.FileStorage).

Three dialects are understood:

- ORB-SLAM2: ``Camera.fx/fy/cx/cy``, ``Camera.k1 k2 p1 p2 [k3]``, ``Camera.bf``, ``DepthMapFactor``, and for
  EuRoC-style stereo the rectification blocks ``LEFT.K/D/R/P``, ``RIGHT.K/D/R/P``, ``LEFT.width/height``.
  ``Camera.*`` is then the *rectified* pinhole camera (ORB-SLAM2 rectifies the images with those blocks).
- ORB-SLAM3 0.x: as above plus ``Camera.type: "PinHole" | "KannalaBrandt8"`` (fisheye ``Camera.k1..k4``),
  ``Camera2.*`` for the right camera, ``Tlr`` (3x4 or 4x4) and ``Tbc``.
- ORB-SLAM3 1.0 (``File.version: "1.0"``): ``Camera1.*`` / ``Camera2.*``, ``Stereo.b``, ``Stereo.T_c1_c2``,
  ``IMU.T_b_c1``, ``RGBD.DepthMapFactor``, ``Stereo.ThDepth``.

Matrices: ``Tlr`` / ``Stereo.T_c1_c2`` map right-camera points to the left camera (T_l_r); ``Tbc`` /
``IMU.T_b_c1`` is the camera pose in the IMU body frame (T_b_c).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from slamkit.errors import CalibrationError, ConfigError
from slamkit.geometry.camera import KannalaBrandtCamera, PinholeCamera
from slamkit.interfaces import Camera
from slamkit.io.cvyaml import CvYaml

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]
U8 = NDArray[np.uint8]

WHAT = "ORB-SLAM settings"


@dataclass(frozen=True)
class OrbExtractorSettings:
    """ORB extractor parameters (ORB-SLAM sec. III-B): features per image, pyramid, FAST thresholds."""

    n_features: int
    scale_factor: float
    n_levels: int
    ini_th_fast: int
    min_th_fast: int


@dataclass(frozen=True)
class StereoRectification:
    """ORB-SLAM2's stereo rectification blocks (outputs of cv2.stereoRectify).

    K_*: (3, 3) raw intrinsics; D_*: (n,) radial-tangential distortion; R_*: (3, 3) rotation from the raw
    to the rectified camera frame (p_rect = R @ p_raw); P_*: (3, 4) rectified projection; size: (W, H) px.
    """

    K_l: F64
    D_l: F64
    R_l: F64
    P_l: F64
    K_r: F64
    D_r: F64
    R_r: F64
    P_r: F64
    size: tuple[int, int]

    @property
    def baseline_m(self) -> float:
        """Distance between the rectified centres: -P_r[0, 3] / P_r[0, 0] (m if the calibration is in m)."""
        return float(-self.P_r[0, 3] / self.P_r[0, 0])

    def maps(self) -> tuple[tuple[F32, F32], tuple[F32, F32]]:
        """cv2.remap tables ((map_x, map_y) left, (map_x, map_y) right) producing the rectified images."""
        left = cv2.initUndistortRectifyMap(self.K_l, self.D_l, self.R_l, self.P_l[:3, :3], self.size, cv2.CV_32FC1)
        right = cv2.initUndistortRectifyMap(self.K_r, self.D_r, self.R_r, self.P_r[:3, :3], self.size, cv2.CV_32FC1)
        lx, ly, rx, ry = (np.asarray(m, dtype=np.float32) for m in (left[0], left[1], right[0], right[1]))
        return (lx, ly), (rx, ry)


@dataclass(frozen=True)
class OrbSlamSettings:
    """What slamkit uses from an ORB-SLAM settings file.

    camera: the (left) camera (rectified one when ``rectification`` is set).
    fps: Camera.fps (Hz) or None. rgb_order: Camera.RGB (True = images are RGB, False = BGR) or None.
    bf: stereo baseline times fx (px * m) or None; baseline_m: stereo/RGB-D baseline in m or None.
    th_depth: ThDepth (close/far threshold in baselines) or None. depth_map_factor: raw depth units per m.
    orb: ORBextractor.* or None. camera_right / T_l_r: right camera and its pose in the left camera frame
    (T_l_r maps right-camera points to the left camera), when the file describes a stereo pair.
    T_b_c: camera pose in the IMU body frame, when given. rectification: ORB-SLAM2's LEFT/RIGHT blocks.
    """

    path: Path
    camera: Camera
    fps: float | None
    rgb_order: bool | None
    bf: float | None
    baseline_m: float | None
    th_depth: float | None
    depth_map_factor: float | None
    orb: OrbExtractorSettings | None
    camera_right: Camera | None
    T_l_r: F64 | None
    T_b_c: F64 | None
    rectification: StereoRectification | None

    def stereo_pair(self) -> tuple[Camera, F64]:
        """(right camera, T_l_r) for a stereo reader.

        A file without a second camera describes a rectified pair (ORB-SLAM2 KITTI/EuRoC files): the right
        camera equals the left one and sits ``baseline_m`` along the left camera's +x axis.
        """
        if self.camera_right is not None and self.T_l_r is not None:
            return self.camera_right, self.T_l_r
        if self.baseline_m is None:
            raise CalibrationError(f"{self.path}: stereo needs Camera.bf (or Stereo.b) in the {WHAT}")
        T_l_r = np.eye(4)
        T_l_r[0, 3] = self.baseline_m
        return self.camera, T_l_r


def _as_se3(path: Path, key: str, M: F64) -> F64:
    if M.shape == (3, 4):
        M = np.vstack([M, [0.0, 0.0, 0.0, 1.0]])
    if M.shape != (4, 4):
        raise CalibrationError(f"{path}: '{key}' is {M.shape}; expected a 3x4 or 4x4 transform")
    R = M[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise CalibrationError(f"{path}: '{key}' rotation block is not a rotation matrix")
    return M.astype(np.float64)


def _make_camera(y: CvYaml, prefix: str, cam_type: str, size: tuple[int, int]) -> Camera:
    try:
        return _build_camera(y, prefix, cam_type, size)
    except ConfigError as exc:  # the camera model names the bad parameter; add the file
        raise CalibrationError(f"{y.path}: {prefix}.*: {exc}") from exc


def _build_camera(y: CvYaml, prefix: str, cam_type: str, size: tuple[int, int]) -> Camera:
    fx, fy, cx, cy = (y.real(f"{prefix}.{k}") for k in ("fx", "fy", "cx", "cy"))
    if fx <= 0 or fy <= 0:
        raise CalibrationError(f"{y.path}: {prefix}.fx and {prefix}.fy must be positive, got {fx}, {fy}")
    w, h = size
    if cam_type == "KannalaBrandt8":
        k = tuple(y.real(f"{prefix}.k{i}") for i in range(1, 5))
        return KannalaBrandtCamera(w, h, fx, fy, cx, cy, k=k)
    if cam_type not in ("PinHole", "Rectified"):
        raise CalibrationError(
            f"{y.path}: Camera.type '{cam_type}' is not supported; expected PinHole, Rectified or KannalaBrandt8"
        )
    names = ("k1", "k2", "p1", "p2")
    dist = [y.real_or(f"{prefix}.{n}", 0.0) or 0.0 for n in names]
    k3 = y.real_or(f"{prefix}.k3", None)
    if k3 is not None:
        dist.append(k3)
    return PinholeCamera(w, h, fx, fy, cx, cy, dist=tuple(dist))


def _image_size(y: CvYaml, image_size: tuple[int, int] | None) -> tuple[int, int]:
    if y.has("Camera.width") and y.has("Camera.height"):
        return y.integer("Camera.width"), y.integer("Camera.height")
    if image_size is None:
        raise CalibrationError(
            f"{y.path}: the {WHAT} lack Camera.width/Camera.height and no image size was given to take them from"
        )
    return int(image_size[0]), int(image_size[1])


def _rectification(y: CvYaml) -> StereoRectification | None:
    keys = [f"{s}.{k}" for s in ("LEFT", "RIGHT") for k in ("K", "D", "R", "P")]
    present = [k for k in keys if y.has(k)]
    if not present:
        return None
    missing = [k for k in keys if not y.has(k)]
    if missing:
        raise CalibrationError(f"{y.path}: stereo rectification is incomplete; missing {', '.join(missing)}")
    size = (y.integer("LEFT.width"), y.integer("LEFT.height"))
    return StereoRectification(
        K_l=y.matrix("LEFT.K", (3, 3)),
        D_l=y.vector("LEFT.D"),
        R_l=y.matrix("LEFT.R", (3, 3)),
        P_l=y.matrix("LEFT.P", (3, 4)),
        K_r=y.matrix("RIGHT.K", (3, 3)),
        D_r=y.vector("RIGHT.D"),
        R_r=y.matrix("RIGHT.R", (3, 3)),
        P_r=y.matrix("RIGHT.P", (3, 4)),
        size=size,
    )


def load_orbslam_settings(path: str | Path, image_size: tuple[int, int] | None = None) -> OrbSlamSettings:
    """Read an ORB-SLAM2/3 settings file.

    image_size: (W, H) px used when the file has no Camera.width/height (ORB-SLAM2 monocular files);
    a size in the file always wins, so a reader can then detect images that disagree with it.
    Raises CalibrationError naming the file (and line for a parse error) and the key at fault.
    """
    p = Path(path)
    y = CvYaml(p, WHAT)
    v1 = y.has("File.version")
    cam_type = y.string_or("Camera.type", "PinHole") or "PinHole"
    prefix = "Camera1" if v1 else "Camera"
    size = _image_size(y, image_size)
    camera = _make_camera(y, prefix, cam_type, size)

    camera_right: Camera | None = None
    T_l_r: F64 | None = None
    if y.has("Camera2.fx"):
        camera_right = _make_camera(y, "Camera2", cam_type, size)
        key = "Stereo.T_c1_c2" if y.has("Stereo.T_c1_c2") else "Tlr"
        T_l_r = _as_se3(p, key, y.matrix(key))

    bf = y.real_or("Camera.bf", None)
    baseline = y.real_or("Stereo.b", None)
    if baseline is None and bf is not None:
        baseline = bf / float(camera.K[0, 0])
    if baseline is None and T_l_r is not None:
        baseline = float(np.linalg.norm(T_l_r[:3, 3]))
    if bf is None and baseline is not None:
        bf = baseline * float(camera.K[0, 0])

    T_b_c: F64 | None = None
    for key in ("IMU.T_b_c1", "Tbc"):
        if y.has(key):
            T_b_c = _as_se3(p, key, y.matrix(key))
            break

    orb: OrbExtractorSettings | None = None
    if y.has("ORBextractor.nFeatures"):
        orb = OrbExtractorSettings(
            n_features=y.integer("ORBextractor.nFeatures"),
            scale_factor=y.real("ORBextractor.scaleFactor"),
            n_levels=y.integer("ORBextractor.nLevels"),
            ini_th_fast=y.integer("ORBextractor.iniThFAST"),
            min_th_fast=y.integer("ORBextractor.minThFAST"),
        )
    rgb = y.real_or("Camera.RGB", None)
    return OrbSlamSettings(
        path=p,
        camera=camera,
        fps=y.real_or("Camera.fps", None),
        rgb_order=None if rgb is None else bool(rgb),
        bf=bf,
        baseline_m=baseline,
        th_depth=y.real_or("Stereo.ThDepth", None) if v1 else y.real_or("ThDepth", None),
        depth_map_factor=y.real_or("RGBD.DepthMapFactor", None) if v1 else y.real_or("DepthMapFactor", None),
        orb=orb,
        camera_right=camera_right,
        T_l_r=T_l_r,
        T_b_c=T_b_c,
        rectification=_rectification(y),
    )
