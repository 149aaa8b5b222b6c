"""``dataset=synthetic``: sequences that slamkit renders itself, with exact ground truth for every sensor.

A scene (``slamkit.io.synthetic.scenes``) gives textured rectangles and a closed camera path; this dataset
renders frame i at t_i = i / fps on demand (random access: ``dataset[i]``; iteration renders on the fly):
grey image (and optionally colour), depth (float32 m along the optical axis, exact), a rectified stereo
right image, and 200 Hz IMU samples computed from the trajectory's derivatives. Everything is a pure
function of ``seed`` and the configuration.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from slamkit.errors import ConfigError
from slamkit.geometry.camera import KannalaBrandtCamera, PinholeCamera
from slamkit.geometry.so3 import so3_exp
from slamkit.io.base import SequenceDataset
from slamkit.io.synthetic.imu import BodyKinematics, ImuNoise, ImuStream, body_kinematics, simulate_imu
from slamkit.io.synthetic.render import MIP_LEVELS, PixelNoise, PlaneRenderer, RenderOutput
from slamkit.io.synthetic.scenes import Scene, build_scene
from slamkit.io.synthetic.textures import TextureBank
from slamkit.io.synthetic.trajectory import CameraTrajectory, PeriodicBSpline
from slamkit.sensors import FrameData, ImuSamples, Trajectory

F64 = NDArray[np.float64]

#: Default pose of the camera in the IMU body frame: the body is x forward, y left, z up (as a vehicle's
#: or a drone's) and the camera sits 5 cm ahead and 2 cm above the IMU. Not identity on purpose, so a
#: visual-inertial pipeline that forgets T_b_c fails visibly.
DEFAULT_T_B_C = np.array(
    [
        [0.0, 0.0, 1.0, 0.05],
        [-1.0, 0.0, 0.0, 0.0],
        [0.0, -1.0, 0.0, 0.02],
        [0.0, 0.0, 0.0, 1.0],
    ]
)

# Noise streams of one frame (seeded by (seed, raw frame, stream)), so any frame renders alone.
_STREAM_GREY, _STREAM_COLOR, _STREAM_RIGHT = 0, 1, 2
# Seed stream of the IMU noise (distinct from every frame's).
_IMU_STREAM = 0x494D55


def _number(value: Any, key: str, *, positive: bool = False, non_negative: bool = False) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"dataset.{key}: expected a number, got {value!r}") from None
    if not math.isfinite(x) or (positive and x <= 0) or (non_negative and x < 0):
        what = "a positive number" if positive else "a number >= 0" if non_negative else "a finite number"
        raise ConfigError(f"dataset.{key}: expected {what}, got {value!r}")
    return x


def _pose(value: Any, key: str) -> F64:
    try:  # rows one by one: Hydra hands over nested ListConfigs, which numpy does not unpack itself
        T = np.array([[float(x) for x in row] for row in value], dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"dataset.{key}: expected a 4x4 list of numbers, got {value!r}") from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ConfigError(f"dataset.{key}: expected a 4x4 list of numbers, got {value!r}")
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0 or not np.allclose(T[3], [0, 0, 0, 1]):
        raise ConfigError(f"dataset.{key}: not a rigid transform (rotation block must be orthonormal, det +1)")
    return T


class SyntheticDataset(SequenceDataset):
    """A rendered sequence of scene ``scene`` (see ``slamkit.io.synthetic.scenes.SCENES``).

    Camera: pinhole ``width`` x ``height`` px with fx, fy (px) and principal point cx, cy (default: the
    image centre, (width - 1) / 2, (height - 1) / 2), or with ``camera_model`` "kannala_brandt" a fisheye camera
    with the same intrinsics and ``kb_k`` = k1..k4 (images rendered through a wide pinhole view, then remapped
    through the fisheye model: see ``_FisheyeRemap``; depth follows with nearest-neighbour sampling).
    ``color``/``depth``/``stereo``/``imu`` switch the optional FrameData fields on. Stereo: a right camera with the
    same intrinsics at ``baseline_m`` along the left camera's x axis (T_l_r translation (baseline_m, 0, 0)), turned
    ``stereo_yaw_deg`` about its y axis (outwards for positive values; 0: a rectified pair, for a pinhole camera).
    IMU: ``imu_rate_hz`` samples of the body frame (pose of the camera in it: ``T_b_c``, default
    DEFAULT_T_B_C) with noise densities imu_* (0 = exact). pixel_noise_std: Gaussian image noise, grey
    levels (geometry stays exact). texels_per_m: texture density override (default: the scene's).
    duration_s: sequence length (default: the scene's). skip / max_frames: see SequenceDataset.

    Images: the grey image is rendered from grey textures (BT.601 luminance of the colour ones) and the
    colour image from the colour textures, each with its own noise; so ``image`` does not change when
    ``color`` is switched on. Depth is noise-free. Rendering is lazy (per frame) and textures are cached.

    Attributes besides the Dataset protocol: ``scene``, ``trajectory`` (CameraTrajectory, exact at any t),
    ``imu_stream`` (all samples and true biases, or None), ``renderer`` (noise-free rendering at any pose),
    ``frame_times_s`` (raw frames' timestamps).
    """

    # Narrower than the Dataset protocol: this dataset always has ground truth.
    camera: PinholeCamera | KannalaBrandtCamera
    ground_truth: Trajectory

    def __init__(
        self,
        scene: str = "room",
        seed: int = 0,
        fps: float = 30.0,
        duration_s: float | None = None,
        width: int = 640,
        height: int = 480,
        fx: float = 470.0,
        fy: float = 470.0,
        cx: float | None = None,
        cy: float | None = None,
        color: bool = False,
        depth: bool = True,
        stereo: bool = False,
        baseline_m: float = 0.12,
        imu: bool = True,
        imu_rate_hz: float = 200.0,
        imu_acc_noise_density: float = 2.0e-3,
        imu_gyro_noise_density: float = 1.6968e-4,
        imu_acc_random_walk: float = 3.0e-3,
        imu_gyro_random_walk: float = 1.9393e-5,
        T_b_c: Sequence[Sequence[float]] | None = None,
        pixel_noise_std: float = 1.0,
        texels_per_m: float | None = None,
        skip: Sequence[int] | None = None,
        max_frames: int | None = None,
        camera_model: str = "pinhole",
        kb_k: Sequence[float] | None = None,
        stereo_yaw_deg: float = 0.0,
    ) -> None:
        if isinstance(seed, bool) or not isinstance(seed, int | np.integer):
            raise ConfigError(f"dataset.seed: expected an integer, got {seed!r}")
        self.seed = int(seed)
        world: Scene = build_scene(str(scene))
        if texels_per_m is not None:
            world = dataclasses.replace(world, texels_per_m=_number(texels_per_m, "texels_per_m", positive=True))
        self.scene = world
        self.name = f"synthetic/{world.name}"
        self.fps = _number(fps, "fps", positive=True)
        duration = world.path.duration_s if duration_s is None else _number(duration_s, "duration_s", positive=True)
        n_raw = math.floor(duration * self.fps + 1e-9)
        if n_raw < 1:
            raise ConfigError(f"dataset.duration_s={duration} at fps={self.fps} gives no frame")
        self.frame_times_s = np.arange(n_raw, dtype=np.float64) / self.fps  # i / fps exactly, as doubles

        pinhole = PinholeCamera(
            width,
            height,
            fx,
            fy,
            (width - 1) / 2.0 if cx is None else cx,
            (height - 1) / 2.0 if cy is None else cy,
        )
        self._fisheye: _FisheyeRemap | None = None
        if camera_model == "pinhole":
            self.camera = pinhole
        elif camera_model == "kannala_brandt":
            if kb_k is None:
                raise ConfigError("dataset.kb_k: missing; expected k1..k4 for camera_model=kannala_brandt")
            self.camera = KannalaBrandtCamera(width, height, fx, fy, pinhole.cx, pinhole.cy, k=list(kb_k))
            self._fisheye = _FisheyeRemap(self.camera)
        else:
            raise ConfigError(f"dataset.camera_model: expected 'pinhole' or 'kannala_brandt', got {camera_model!r}")
        self.color, self.depth, self.stereo, self.imu = bool(color), bool(depth), bool(stereo), bool(imu)
        self.pixel_noise_std = _number(pixel_noise_std, "pixel_noise_std", non_negative=True)
        self._pixel_noise = PixelNoise(self.pixel_noise_std)
        if self.stereo:
            b = _number(baseline_m, "baseline_m", positive=True)
            self.camera_right = self.camera
            self.T_l_r = np.eye(4)
            self.T_l_r[0, 3] = b
            yaw = _number(stereo_yaw_deg, "stereo_yaw_deg")
            self.T_l_r[:3, :3] = so3_exp(np.array([0.0, math.radians(yaw), 0.0]))
        else:
            self.camera_right, self.T_l_r = None, None

        path = world.path
        look = None if path.look_at_m is None else PeriodicBSpline(np.asarray(path.look_at_m), path.period_s)
        self.trajectory = CameraTrajectory(
            PeriodicBSpline(np.asarray(path.waypoints_m), path.period_s),
            look,
            path.look_ahead_s,
            math.radians(path.yaw_offset_deg),
        )
        self._T_w_c = self.trajectory.T_w_c(self.frame_times_s)  # (N, 4, 4) exact pose of every raw frame
        self.ground_truth = Trajectory(self.frame_times_s.copy(), self._T_w_c.copy())

        self.T_b_c = DEFAULT_T_B_C.copy() if T_b_c is None else _pose(T_b_c, "T_b_c")
        self.imu_stream: ImuStream | None = None
        if self.imu:
            noise = ImuNoise(
                float(imu_acc_noise_density),
                float(imu_gyro_noise_density),
                float(imu_acc_random_walk),
                float(imu_gyro_random_walk),
            )
            rate = _number(imu_rate_hz, "imu_rate_hz", positive=True)
            rng = np.random.default_rng([self.seed & 0xFFFFFFFF, _IMU_STREAM])
            self.imu_stream = simulate_imu(self.trajectory, self.T_b_c, rate, float(self.frame_times_s[-1]), noise, rng)
        else:
            self.T_b_c = None

        if self._fisheye is None:
            self.renderer = PlaneRenderer(world, TextureBank(self.seed, MIP_LEVELS), self.camera.K, width, height)
        else:
            f = self._fisheye
            self.renderer = PlaneRenderer(world, TextureBank(self.seed, MIP_LEVELS), f.K_wide, f.width, f.height)
        self._setup_selection(skip, max_frames)

    def prepare_playback(self) -> None:
        """Build the whole world now (every texture), so that playing the sequence costs rendering only.

        The threaded runner calls this before its clock starts: the world exists before the camera looks at it,
        and a real-time run should not pay for generating a wall's texture the first time the wall comes into
        view (up to half a second of one core, which a live camera never costs)."""
        self.renderer.prepare_textures(grey=True, color=self.color)

    def _n_raw(self) -> int:
        return int(self.frame_times_s.shape[0])

    def body_state(self, t_s: ArrayLike) -> BodyKinematics:
        """Exact IMU-body state (pose, velocity, acceleration, angular velocity) at times t_s (M,) s."""
        T_b_c = DEFAULT_T_B_C if self.T_b_c is None else self.T_b_c
        return body_kinematics(self.trajectory, T_b_c, np.atleast_1d(np.asarray(t_s, dtype=np.float64)))

    def render_raw(self, raw_index: int, labels: bool = False) -> RenderOutput:
        """Noise-free render of raw frame ``raw_index`` (grey, colour if enabled, depth, optional labels)."""
        return self._render(self._T_w_c[raw_index], color=self.color, labels=labels)

    def _render(self, T_w_c: F64, color: bool, labels: bool = False) -> RenderOutput:
        """The camera's view at T_w_c (4, 4): the renderer's pinhole image, or its remap through the fisheye."""
        out = self.renderer.render(T_w_c, grey=True, color=color, labels=labels)
        return out if self._fisheye is None else self._fisheye.apply(out)

    def _noisy(self, image: NDArray[np.uint8], raw_index: int, stream: int) -> NDArray[np.uint8]:
        rng = np.random.default_rng([self.seed & 0xFFFFFFFF, raw_index, stream])
        return self._pixel_noise.apply(image, rng)

    def _imu_for(self, raw_index: int, out_index: int) -> ImuSamples:
        if self.imu_stream is None:
            return ImuSamples.empty()
        # (previous yielded frame, this frame]: every sample reaches the pipeline once, even across a skip.
        prev = self._selected[out_index - 1] if out_index > 0 else raw_index - 1
        t_prev = float(prev) / self.fps if prev >= 0 else -math.inf
        return self.imu_stream.between(t_prev, float(self.frame_times_s[raw_index]))

    def _load(self, raw_index: int, out_index: int) -> FrameData:
        T_w_c = self._T_w_c[raw_index]
        left = self._render(T_w_c, color=self.color)
        right = None
        if self.T_l_r is not None:
            right_view = self._render(T_w_c @ self.T_l_r, color=False)
            assert right_view.grey is not None
            right = self._noisy(right_view.grey, raw_index, _STREAM_RIGHT)
        assert left.grey is not None
        return FrameData(
            index=out_index,
            timestamp_s=float(self.frame_times_s[raw_index]),
            image=self._noisy(left.grey, raw_index, _STREAM_GREY),
            color=None if left.color is None else self._noisy(left.color, raw_index, _STREAM_COLOR),
            depth_m=left.depth_m if self.depth else None,
            image_right=right,
            imu=self._imu_for(raw_index, out_index),
            T_w_c_gt=T_w_c.copy(),
            source=f"{self.name} (seed {self.seed}) frame {raw_index}",
        )


class _FisheyeRemap:
    """Images of a Kannala-Brandt camera from a wide pinhole render: every fisheye pixel's bearing (the camera's
    ``unproject``) is looked up in a pinhole view with the same centre and fx, fy (so the centre keeps its
    resolution) large enough for the rays up to ``max_angle_deg`` from the axis; rays beyond it are black, depth 0.

    K_wide: (3, 3) the pinhole render's intrinsics; width / height: its size, px; map_u / map_v: (H, W) float32
    pinhole coordinates of each fisheye pixel (cv2.remap).
    """

    def __init__(self, camera: KannalaBrandtCamera, max_angle_deg: float = 70.0) -> None:
        h, w = camera.height, camera.width
        vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
        b = camera.unproject(np.stack([uu.ravel(), vv.ravel()], axis=1))
        cos_max = math.cos(math.radians(max_angle_deg))
        with np.errstate(invalid="ignore", divide="ignore"):
            ok = np.isfinite(b).all(axis=1) & (b[:, 2] >= cos_max)
            x = np.where(ok, b[:, 0] / b[:, 2], np.nan)
            y = np.where(ok, b[:, 1] / b[:, 2], np.nan)
        half_x = float(np.nanmax(np.abs(x))) * camera.fx + 2.0
        half_y = float(np.nanmax(np.abs(y))) * camera.fy + 2.0
        self.width, self.height = int(2 * math.ceil(half_x)), int(2 * math.ceil(half_y))
        cx, cy = (self.width - 1) / 2.0, (self.height - 1) / 2.0
        self.K_wide = np.array([[camera.fx, 0.0, cx], [0.0, camera.fy, cy], [0.0, 0.0, 1.0]])
        self.map_u = np.where(ok, camera.fx * x + cx, -10.0).reshape(h, w).astype(np.float32)
        self.map_v = np.where(ok, camera.fy * y + cy, -10.0).reshape(h, w).astype(np.float32)

    def apply(self, view: RenderOutput) -> RenderOutput:
        """The fisheye image of a pinhole render (grey and colour bilinear, depth and labels nearest)."""

        def remap(img: NDArray[Any] | None, interpolation: int) -> NDArray[Any] | None:
            if img is None or img.size == 0:
                return img
            return cv2.remap(img, self.map_u, self.map_v, interpolation, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

        labels = view.labels
        if labels is not None and labels.size:
            lab = cv2.remap(
                labels.astype(np.float32),
                self.map_u,
                self.map_v,
                cv2.INTER_NEAREST,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=-1,
            )
            labels = np.asarray(lab, np.int32)
        depth = remap(view.depth_m, cv2.INTER_NEAREST)
        assert depth is not None
        return RenderOutput(remap(view.grey, cv2.INTER_LINEAR), remap(view.color, cv2.INTER_LINEAR), depth, labels)
