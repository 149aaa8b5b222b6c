"""EuRoC MAV reader (Burri et al., IJRR 2016), ASL folder layout.

``root`` is the folder holding ``mav0/``, which holds ``cam0/`` (and ``cam1/``) with ``data.csv``
(``t[ns],filename``), ``data/*.png`` and ``sensor.yaml`` (intrinsics, radial-tangential or equidistant
distortion, ``T_BS`` = pose of the sensor in the body frame, resolution, rate); ``imu0/data.csv``
(``t[ns], w_x, w_y, w_z [rad/s], a_x, a_y, a_z [m/s^2]``) and, when present,
``state_groundtruth_estimate0/data.csv`` (body poses).

Ground truth is always returned as **cam0 poses** T_w_c: EuRoC's ground truth is the pose of the body
frame B (the IMU), so T_w_c = T_w_B @ T_B_cam0 with T_B_cam0 = cam0's ``T_BS``. A TUM-format file given by
``groundtruth: PATH`` is taken as body poses too unless ``groundtruth_frame: camera``.

With ``stereo: true`` cam1 frames are paired with cam0 frames of the same timestamp (cam0 frames without a
partner are dropped, with a warning), ``T_l_r`` = inv(T_B_cam0) @ T_B_cam1. With ``settings`` holding
ORB-SLAM2's rectification blocks (``LEFT.*``/``RIGHT.*``) the images are rectified and the camera frame
becomes the rectified left camera (T_b_c, T_l_r and ground truth follow).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from slamkit.errors import CalibrationError, ConfigError
from slamkit.geometry.camera import KannalaBrandtCamera, PinholeCamera
from slamkit.interfaces import Camera
from slamkit.io.base import SequenceDataset
from slamkit.io.calibration import load_settings, orb_extractor_from_options
from slamkit.io.cvyaml import CvYaml
from slamkit.io.ground_truth import poses_at, transform_trajectory
from slamkit.io.images import load_image
from slamkit.io.orbslam_settings import StereoRectification
from slamkit.io.textfiles import (
    StampedFiles,
    check_columns,
    check_increasing,
    float_columns,
    ns_column,
    read_rows,
    read_stamped_files,
    require_dir,
    require_file,
    row_lines,
)
from slamkit.io.timing import associate_stamps, imu_between
from slamkit.io.trajectory_io import read_euroc_groundtruth, read_tum_trajectory
from slamkit.sensors import FrameData, ImuSamples

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
U8 = NDArray[np.uint8]

#: Pairs cam0/cam1 frames: EuRoC's cameras are hardware-triggered, stamps agree to the nanosecond.
STEREO_SYNC_TOL_S = 1e-3


class EurocSensor:
    """A camera's ``sensor.yaml``: camera model, T_B_S (pose of the camera in the body frame), rate (Hz)."""

    def __init__(self, path: Path) -> None:
        y = CvYaml(path, "EuRoC camera sensor.yaml")
        self.path = path
        self.T_B_S: F64 = y.matrix("T_BS", (4, 4))
        width, height = (int(v) for v in y.vector("resolution", 2))
        fx, fy, cx, cy = (float(v) for v in y.vector("intrinsics", 4))
        model = y.string_or("camera_model", "pinhole")
        if model != "pinhole":
            raise CalibrationError(f"{path}: camera_model '{model}' is not supported; expected pinhole")
        dist_model = y.string_or("distortion_model", "radial-tangential")
        coeffs = tuple(float(v) for v in y.vector("distortion_coefficients"))
        self.camera: Camera
        if dist_model == "radial-tangential":
            if len(coeffs) not in (4, 5):
                raise CalibrationError(f"{path}: radial-tangential needs 4 or 5 distortion_coefficients")
            self.camera = PinholeCamera(width, height, fx, fy, cx, cy, dist=coeffs)
        elif dist_model == "equidistant":
            if len(coeffs) != 4:
                raise CalibrationError(f"{path}: equidistant needs 4 distortion_coefficients")
            self.camera = KannalaBrandtCamera(width, height, fx, fy, cx, cy, k=coeffs)
        else:
            raise CalibrationError(
                f"{path}: distortion_model '{dist_model}' is not supported; expected radial-tangential or equidistant"
            )
        self.rate_hz = float(y.real_or("rate_hz", 20.0) or 20.0)


def read_euroc_imu(path: Path) -> ImuSamples:
    """``imu0/data.csv``: t [ns], gyro x y z [rad/s], acc x y z [m/s^2] -> ImuSamples in the IMU frame."""
    what = "EuRoC IMU 't[ns], w_x, w_y, w_z, a_x, a_y, a_z'"
    rows = read_rows(path, sep=",", what=what)
    check_columns(path, rows, 7, what)
    t_s = ns_column(path, rows, 0, what)
    vals = float_columns(path, rows, range(1, 7), what)
    check_increasing(path, t_s, row_lines(rows), what="IMU timestamps")
    return ImuSamples(t_s, vals[:, 3:6].copy(), vals[:, 0:3].copy())


def _rotation_se3(R: F64) -> F64:
    T = np.eye(4)
    T[:3, :3] = R
    return T


class EurocDataset(SequenceDataset):
    """A EuRoC MAV sequence: grey cam0 (+ cam1) images, IMU between frames, ground truth as cam0 poses.

    Constructor keywords are the keys of conf/dataset/euroc.yaml:
    root: folder holding mav0/. stereo: also read cam1. settings: ORB-SLAM settings whose camera replaces
    sensor.yaml's (and whose LEFT/RIGHT blocks, if any, rectify a stereo pair). groundtruth: a TUM-format
    file used instead of (or in the absence of) state_groundtruth_estimate0/data.csv. groundtruth_frame:
    'body' (the file holds T_w_B, EuRoC's convention) or 'camera' (already cam0 T_w_c). imu: read imu0.
    gt_max_gap_s: interpolate ground truth only between samples at most this far apart (s).
    orb_extractor: ORB-SLAM's extractor settings for EuRoC (``orb_settings``; the settings file's win).
    """

    def __init__(
        self,
        root: str | Path,
        skip: Sequence[int] | None = None,
        max_frames: int | None = None,
        stereo: bool = False,
        settings: str | Path | None = None,
        orb_extractor: Mapping[str, Any] | None = None,
        groundtruth: str | Path | None = None,
        groundtruth_frame: str = "body",
        imu: bool = True,
        gt_max_gap_s: float = 0.1,
    ) -> None:
        self.root = require_dir(Path(root), "EuRoC sequence (dataset.root)")
        mav0 = require_dir(self.root / "mav0", f"EuRoC sequence {self.root}: mav0/")
        self.name = f"euroc:{self.root.name}"
        self.stereo = bool(stereo)
        if groundtruth_frame not in ("body", "camera"):
            raise ConfigError(f"dataset.groundtruth_frame: expected 'body' or 'camera', got {groundtruth_frame!r}")

        sensor0 = EurocSensor(mav0 / "cam0" / "sensor.yaml")
        cam0 = self._camera_list(mav0, "cam0")
        T_B_c: F64 = sensor0.T_B_S
        self.camera = sensor0.camera
        self._calib = str(sensor0.path)
        self.fps = sensor0.rate_hz

        self._right_files: list[Path] | None = None
        self._calib_right = ""
        sensor1: EurocSensor | None = None
        keep = np.arange(len(cam0), dtype=np.int64)
        if self.stereo:
            sensor1 = EurocSensor(mav0 / "cam1" / "sensor.yaml")
            cam1 = read_stamped_files(
                mav0 / "cam1" / "data.csv", mav0 / "cam1" / "data", sep=",", ns_stamps=True, what="EuRoC cam1"
            )
            ia, ib = associate_stamps(cam0.t_s, cam1.t_s, STEREO_SYNC_TOL_S)
            if ia.size < len(cam0):
                log.warning("%s: %d cam0 frames have no cam1 partner and are dropped", self.root, len(cam0) - ia.size)
            keep = ia
            paired = StampedFiles(cam1.list_path, cam1.t_s[ib], [cam1.files[int(j)] for j in ib], cam1.lines[ib])
            paired.check_files_exist()
            self._right_files = paired.files
            self.camera_right = sensor1.camera
            self._calib_right = str(sensor1.path)
            self.T_l_r = np.linalg.inv(sensor0.T_B_S) @ sensor1.T_B_S
        StampedFiles(
            cam0.list_path, cam0.t_s[keep], [cam0.files[int(i)] for i in keep], cam0.lines[keep]
        ).check_files_exist()
        self._t_s: F64 = cam0.t_s[keep]
        self._files = [cam0.files[int(i)] for i in keep]

        self._maps: tuple[tuple[NDArray[np.float32], NDArray[np.float32]], ...] | None = None
        loaded = load_settings(settings, (self.camera.width, self.camera.height))
        self.orb_settings = orb_extractor_from_options(orb_extractor, loaded)
        if loaded is not None:
            self.camera = loaded.camera
            self._calib = str(loaded.path)
            self.fps = loaded.fps or self.fps
            # Camera.* of a file with LEFT/RIGHT blocks is the rectified camera: rectify even a monocular run.
            if loaded.rectification is not None:
                T_B_c = T_B_c @ self._use_rectification(loaded.rectification)
            elif self.stereo:
                self.camera_right, self.T_l_r = loaded.stereo_pair()
            if self.stereo:
                self._calib_right = str(loaded.path)

        # IMU samples are in the imu0 frame; T_b_c is the camera in that frame (EuRoC: imu0 = body).
        imu_dir = mav0 / "imu0"
        self._imu: ImuSamples | None = None
        self.T_b_c = T_B_c
        if imu and imu_dir.is_dir():
            T_B_imu = CvYaml(imu_dir / "sensor.yaml", "EuRoC IMU sensor.yaml").matrix("T_BS", (4, 4))
            self.T_b_c = np.linalg.inv(T_B_imu) @ T_B_c
            self._imu = read_euroc_imu(imu_dir / "data.csv")
        elif imu:
            log.warning("%s has no imu0/: frames carry no IMU samples", mav0)

        gt_csv = mav0 / "state_groundtruth_estimate0" / "data.csv"
        if groundtruth:
            traj = read_tum_trajectory(require_file(Path(groundtruth), "dataset.groundtruth"))
            # Body poses: T_w_c = T_w_B @ T_B_c. Raw cam0 poses: only a rectification rotation (if any) remains.
            T_right = T_B_c if groundtruth_frame == "body" else np.linalg.inv(sensor0.T_B_S) @ T_B_c
            self.ground_truth = transform_trajectory(traj, T_right)
        elif gt_csv.is_file():
            self.ground_truth = transform_trajectory(read_euroc_groundtruth(gt_csv), T_B_c)
        else:
            self.ground_truth = None
        self._gt = (
            poses_at(self.ground_truth, self._t_s, float(gt_max_gap_s))
            if self.ground_truth is not None
            else [None] * len(self._t_s)
        )
        self._setup_selection(skip, max_frames)

    @staticmethod
    def _camera_list(mav0: Path, cam: str) -> StampedFiles:
        folder = require_dir(mav0 / cam, f"EuRoC {cam}/")
        return read_stamped_files(folder / "data.csv", folder / "data", sep=",", ns_stamps=True, what=f"EuRoC {cam}")

    def _use_rectification(self, rect: StereoRectification) -> F64:
        """Switch to rectified images; returns T_raw_rect, the rectified left frame in the raw cam0 frame."""
        if rect.size != (self.camera.width, self.camera.height):
            raise CalibrationError(
                f"{self._calib}: LEFT.width/height {rect.size} disagree with the camera's "
                f"{self.camera.width}x{self.camera.height}"
            )
        self._maps = rect.maps()
        if self.stereo:
            self.camera_right = self.camera
            T_l_r = np.eye(4)
            T_l_r[0, 3] = rect.baseline_m
            self.T_l_r = T_l_r
        return _rotation_se3(rect.R_l.T)  # p_rect = R_l p_raw

    def _n_raw(self) -> int:
        return int(self._t_s.shape[0])

    def timestamps(self) -> F64:
        """(N,) s capture times of the yielded frames."""
        return self._t_s[self.raw_indices()]

    def _raw_size(self) -> tuple[int, int]:
        if self._maps is not None:
            return int(self._maps[0][0].shape[1]), int(self._maps[0][0].shape[0])
        return self.camera.width, self.camera.height

    def _rectify(self, image: U8, side: int) -> U8:
        if self._maps is None:
            return image
        map_x, map_y = self._maps[side]
        return np.asarray(cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR), dtype=np.uint8)

    def _load(self, raw_index: int, out_index: int) -> FrameData:
        path = self._files[raw_index]
        t = float(self._t_s[raw_index])
        grey = self._rectify(load_image(path, self._raw_size(), self._calib, keep_color=False).grey, 0)
        right = None
        if self._right_files is not None:
            rsize = (
                self._raw_size() if self.camera_right is None else (self.camera_right.width, self.camera_right.height)
            )
            right_path = self._right_files[raw_index]
            right = self._rectify(load_image(right_path, rsize, self._calib_right, keep_color=False).grey, 1)
        imu = ImuSamples.empty()
        if self._imu is not None:
            # (previous yielded frame, this frame]; the first frame gets one frame period before it.
            sel = self.raw_indices()
            t_prev = float(self._t_s[sel[out_index - 1]]) if out_index > 0 else t - 1.0 / self.fps
            imu = imu_between(self._imu, t_prev, t)
        return FrameData(
            index=out_index,
            timestamp_s=t,
            image=grey,
            image_right=right,
            imu=imu,
            T_w_c_gt=self._gt[raw_index],
            source=str(path),
        )
