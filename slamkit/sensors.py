"""Plain sensor data exchanged between datasets and the pipeline.

Conventions (see docs/conventions.md): ``T_a_b`` maps points from frame b to frame a
(``p_a = T_a_b @ p_b``); poses are float64 4x4 homogeneous matrices; times are seconds (float64);
pixel coordinates are float32; depth is metres (float32, 0 or NaN where unknown).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]
U8 = NDArray[np.uint8]


@dataclass(frozen=True)
class ImuSamples:
    """IMU measurements in the IMU (body) frame ``b``.

    t_s: (N,) s, strictly increasing.
    acc_mps2: (N, 3) m/s^2, specific force (what an accelerometer measures: a_b - R_b_w @ g_w).
    gyro_radps: (N, 3) rad/s, angular velocity of the body in the body frame.
    """

    t_s: F64
    acc_mps2: F64
    gyro_radps: F64

    @staticmethod
    def empty() -> ImuSamples:
        return ImuSamples(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))

    def __len__(self) -> int:
        return int(self.t_s.shape[0])


@dataclass(frozen=True)
class FrameData:
    """One timestamped sensor packet, as a Dataset yields it.

    index: position in the (possibly skipped) sequence, 0-based, monotonic.
    timestamp_s: capture time of the (left) image, s.
    image: (H, W) uint8 grey image of the (left) camera.
    color: (H, W, 3) uint8 BGR image, when the dataset has colour.
    depth_m: (H, W) float32 depth along the optical axis in metres, registered to ``image``; 0 = unknown.
    image_right: (H, W) uint8 grey right image (stereo), rectified or raw as the dataset provides.
    imu: IMU samples with t in (previous frame's timestamp, this frame's timestamp].
    T_w_c_gt: (4, 4) ground-truth pose of the (left) camera in the world, when known exactly for this frame.
    source: where the frame came from (file path or a description), for error messages.
    """

    index: int
    timestamp_s: float
    image: U8
    color: U8 | None = None
    depth_m: F32 | None = None
    image_right: U8 | None = None
    imu: ImuSamples = field(default_factory=ImuSamples.empty)
    T_w_c_gt: F64 | None = None
    source: str = ""


@dataclass(frozen=True)
class Trajectory:
    """A timestamped sequence of camera poses in one world frame.

    t_s: (N,) s, non-decreasing.
    T_w_c: (N, 4, 4) float64, pose of the camera in the world (maps camera points to world points).
    """

    t_s: F64
    T_w_c: F64

    def __post_init__(self) -> None:
        if self.t_s.ndim != 1 or self.T_w_c.shape != (self.t_s.shape[0], 4, 4):
            raise ValueError(
                f"Trajectory expects t_s (N,) and T_w_c (N, 4, 4); got {self.t_s.shape} and {self.T_w_c.shape}"
            )

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    @property
    def positions_m(self) -> F64:
        """(N, 3) m: the camera centres in the world frame (translation of T_w_c)."""
        return self.T_w_c[:, :3, 3]


@dataclass(frozen=True)
class FrameRecords:
    """A map's frames as ORB-SLAM records its trajectory (System::SaveTrajectoryTUM: mlRelativeFramePoses,
    mlpReferences, mlFrameTimes): each frame as its reference keyframe and its pose relative to it, so the frames
    follow every later correction of the keyframes. What a map file keeps of a session's frames (docs/atlas.md,
    "Multi-session") and what a later session's trajectory recorders start from.

    t_s: (N,) s, the frames' timestamps, non-decreasing. frame_index: (N,) int64, each frame's index in its session.
    ref_kf_id: (N,) int64, the reference keyframe of each frame (a keyframe of the map). T_c_r: (N, 4, 4) float64,
    the frame's pose relative to it, T_c_w @ T_w_r (a monocular map's translation in the map's scale).
    """

    t_s: F64
    frame_index: NDArray[np.int64]
    ref_kf_id: NDArray[np.int64]
    T_c_r: F64

    def __post_init__(self) -> None:
        n = self.t_s.shape[0] if self.t_s.ndim == 1 else -1
        if n < 0 or self.frame_index.shape != (n,) or self.ref_kf_id.shape != (n,) or self.T_c_r.shape != (n, 4, 4):
            raise ValueError(
                f"FrameRecords expects t_s (N,), frame_index (N,), ref_kf_id (N,), T_c_r (N, 4, 4); got "
                f"{self.t_s.shape}, {self.frame_index.shape}, {self.ref_kf_id.shape}, {self.T_c_r.shape}"
            )

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    @staticmethod
    def empty() -> FrameRecords:
        """No frame."""
        return FrameRecords(np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 4, 4)))
