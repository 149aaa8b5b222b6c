"""The Dataset contract: every registered dataset reader must pass these tests.

Parametrized over ``ComponentRegistry.discover().components("dataset")``, each built from its default config node
(conf/dataset/NAME.yaml, or the plugin's node) with only the keys a reader cannot default: the sequence it reads
(``root``, ../shared/datasets for the real-data readers, skipped with a reason when absent; small image and video
files written with OpenCV into tmp_path for ``folder``, ``video`` and ``camera``, whose device is a video file played
as a live stream) and a few frames (``max_frames``) to stay fast.

What a reader promises (slamkit/interfaces.py Dataset, slamkit/sensors.py FrameData):
- ``len(ds)`` is the number of frames iteration yields (a live source, ``live = True``, has none: its ``len`` raises
  TypeError); indices run 0, 1, 2, ...; timestamps strictly increase.
- every image is (H, W) uint8 with (W, H) the camera's size; colour (H, W, 3) and depth (H, W) when present.
- calibration is sane: K upper triangular with fx, fy > 0 and the principal point inside the image; a right
  camera comes with T_l_r (both or neither), SE(3) with a non-zero baseline; T_b_c, when given, is SE(3); fps > 0.
- ground truth, when present, is SE(3) at strictly increasing times and covers every frame's timestamp (so the
  evaluation can associate each tracked frame); a frame's T_w_c_gt, when given, is SE(3).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml

from slamkit.interfaces import Dataset
from slamkit.plugins import ComponentRegistry
from slamkit.runtime.source import frame_count, is_live
from slamkit.sensors import FrameData

REGISTRY = ComponentRegistry.discover()
NAMES = [c.spec.name for c in REGISTRY.components("dataset")]
CONF = Path(__file__).resolve().parents[2] / "conf" / "dataset"
N_FRAMES = 6
SE3_TOL = 1e-6


def default_node(name: str) -> dict[str, Any]:
    """The component's default config node: its YAML in conf/dataset/ or the node its plugin registers."""
    comp = REGISTRY.get("dataset", name)
    path = CONF / f"{name}.yaml"
    node = dict(yaml.safe_load(path.read_text())) if comp.spec.config is None and path.is_file() else {}
    return {**node, **comp.config_node()}


def _texture(seed: int, w: int = 320, h: int = 240) -> np.ndarray:
    """A textured BGR image (blurred noise, contrast stretched) that shifts a little with ``seed``."""
    rng = np.random.default_rng(0)
    base = cv2.GaussianBlur(rng.integers(0, 256, (h + 40, w + 40), dtype=np.uint8), (0, 0), 2.0).astype(np.float64)
    base = np.clip((base - base.mean()) * 6 + 128, 0, 255).astype(np.uint8)
    crop = base[seed : seed + h, 2 * seed : 2 * seed + w]
    return np.asarray(cv2.cvtColor(crop, cv2.COLOR_GRAY2BGR))


CAMERA = {"fx": 300.0, "fy": 300.0, "cx": 159.5, "cy": 119.5}


def _synthetic(_shared: Callable[[], Path], _tmp: Path) -> dict[str, Any]:
    return {"seed": 0, "max_frames": N_FRAMES, "imu": False}


def _tum(shared: Callable[[], Path], _tmp: Path) -> dict[str, Any]:
    return {"root": str(shared() / "tum_rgbd/rgbd_dataset_freiburg1_xyz"), "max_frames": N_FRAMES}


def _euroc(shared: Callable[[], Path], _tmp: Path) -> dict[str, Any]:
    return {"root": str(shared() / "euroc/V1_01_easy"), "max_frames": N_FRAMES, "stereo": True}


def _kitti(shared: Callable[[], Path], _tmp: Path) -> dict[str, Any]:
    return {"root": str(shared() / "kitti"), "sequence": "07", "max_frames": N_FRAMES}


def _folder(_shared: Callable[[], Path], tmp: Path) -> dict[str, Any]:
    folder = tmp / "images"
    folder.mkdir()
    for i in range(N_FRAMES + 2):
        assert cv2.imwrite(str(folder / f"{i:06d}.png"), _texture(i))
    return {"root": str(folder), "fps": 10.0, "camera": dict(CAMERA), "max_frames": N_FRAMES}


def _clip(tmp: Path) -> Path:
    path = tmp / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 15.0, (320, 240))
    for i in range(N_FRAMES + 2):
        writer.write(_texture(i))
    writer.release()
    return path


def _video(_shared: Callable[[], Path], tmp: Path) -> dict[str, Any]:
    return {"root": str(_clip(tmp)), "camera": dict(CAMERA), "max_frames": N_FRAMES}


def _camera(_shared: Callable[[], Path], tmp: Path) -> dict[str, Any]:
    return {"device": str(_clip(tmp)), "camera": dict(CAMERA), "max_frames": N_FRAMES}


#: name -> the keys a reader needs to read something (the rest of its default node is kept).
INPUTS: dict[str, Callable[[Callable[[], Path], Path], dict[str, Any]]] = {
    "synthetic": _synthetic,
    "tum_rgbd": _tum,
    "euroc": _euroc,
    "kitti": _kitti,
    "folder": _folder,
    "video": _video,
    "camera": _camera,
}


#: readers of recorded sequences: their tests need ../shared/datasets (skipped with the reason when absent)
SHARED = {"tum_rgbd", "euroc", "kitti"}


@pytest.fixture(
    scope="module", params=[pytest.param(n, marks=pytest.mark.shared_data) if n in SHARED else n for n in NAMES]
)
def built(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> tuple[Dataset, list[FrameData]]:
    name = request.param
    if name not in INPUTS:
        pytest.fail(f"dataset={name} is registered but this contract has no input for it: add one to INPUTS")

    def shared() -> Path:
        return Path(request.getfixturevalue("shared_datasets"))

    node = {**default_node(name), **INPUTS[name](shared, tmp_path_factory.mktemp(name))}
    ds = REGISTRY.instantiate("dataset", node)
    return ds, list(ds)


def assert_se3(T: np.ndarray, what: str) -> None:
    T = np.asarray(T)
    assert T.shape == (4, 4) and T.dtype == np.float64, f"{what}: expected (4, 4) float64, got {T.shape} {T.dtype}"
    R = T[:3, :3]
    assert np.allclose(R.T @ R, np.eye(3), atol=SE3_TOL) and abs(np.linalg.det(R) - 1) < SE3_TOL, f"{what}: R not SO(3)"
    assert np.array_equal(T[3], [0.0, 0.0, 0.0, 1.0]) and np.isfinite(T).all(), f"{what}: not homogeneous/finite"


def test_is_a_dataset(built: tuple[Dataset, list[FrameData]]) -> None:
    ds, _ = built
    assert isinstance(ds, Dataset)
    assert isinstance(ds.name, str) and ds.name


def test_length_matches_iteration_and_indices(built: tuple[Dataset, list[FrameData]]) -> None:
    ds, frames = built
    if is_live(ds):
        assert frame_count(ds) is None and len(frames) == N_FRAMES
        with pytest.raises(TypeError):
            len(ds)
    else:
        assert len(ds) == len(frames) == N_FRAMES
    assert [f.index for f in frames] == list(range(len(frames)))
    assert [f.index for f in ds] == [f.index for f in frames]  # a second pass gives the same sequence


def test_timestamps_strictly_increase(built: tuple[Dataset, list[FrameData]]) -> None:
    _, frames = built
    t = np.array([f.timestamp_s for f in frames])
    assert np.isfinite(t).all() and np.all(np.diff(t) > 0), t


def test_images_have_the_camera_size(built: tuple[Dataset, list[FrameData]]) -> None:
    ds, frames = built
    shape = (ds.camera.height, ds.camera.width)
    for f in frames:
        assert f.image.dtype == np.uint8 and f.image.shape == shape, (f.index, f.image.shape, shape)
        assert f.image.std() > 0, f"frame {f.index}: a constant image"
        if f.color is not None:
            assert f.color.dtype == np.uint8 and f.color.shape == (*shape, 3)
        if f.depth_m is not None:
            assert f.depth_m.dtype == np.float32 and f.depth_m.shape == shape
        if f.image_right is not None:
            assert ds.camera_right is not None
            assert f.image_right.shape == (ds.camera_right.height, ds.camera_right.width)


def test_calibration_is_sane(built: tuple[Dataset, list[FrameData]]) -> None:
    ds, _ = built
    for cam in [ds.camera] + ([ds.camera_right] if ds.camera_right is not None else []):
        K = np.asarray(cam.K)
        assert K.shape == (3, 3) and np.isfinite(K).all()
        assert K[0, 0] > 0 and K[1, 1] > 0 and K[1, 0] == K[2, 0] == K[2, 1] == 0 and K[2, 2] == 1
        assert 0 < K[0, 2] < cam.width and 0 < K[1, 2] < cam.height
        # the camera maps its own principal ray to the principal point
        assert np.allclose(cam.project(np.array([[0.0, 0.0, 1.0]])), K[:2, 2], atol=1e-6)
    assert (ds.camera_right is None) == (ds.T_l_r is None), "camera_right and T_l_r come together"
    if ds.T_l_r is not None:
        assert_se3(ds.T_l_r, "T_l_r")
        assert np.linalg.norm(ds.T_l_r[:3, 3]) > 0, "a stereo pair needs a baseline"
    if ds.T_b_c is not None:
        assert_se3(ds.T_b_c, "T_b_c")
    assert ds.fps > 0


def test_ground_truth_covers_the_frames_and_is_se3(built: tuple[Dataset, list[FrameData]]) -> None:
    ds, frames = built
    gt = ds.ground_truth
    for f in frames:
        if f.T_w_c_gt is not None:
            assert_se3(f.T_w_c_gt, f"frame {f.index} T_w_c_gt")
    if gt is None:
        assert all(f.T_w_c_gt is None for f in frames), "per-frame ground truth without a ground-truth trajectory"
        return
    assert len(gt) >= 2 and np.all(np.diff(gt.t_s) > 0)
    for i in range(0, len(gt), max(1, len(gt) // 50)):
        assert_se3(gt.T_w_c[i], f"ground_truth[{i}]")
    t = np.array([f.timestamp_s for f in frames])
    assert gt.t_s[0] <= t.min() + 0.05 and t.max() - 0.05 <= gt.t_s[-1], (
        f"ground truth spans [{gt.t_s[0]}, {gt.t_s[-1]}] s, frames [{t.min()}, {t.max()}] s"
    )


# ---- the suite catches a broken reader ---------------------------------------------------------------------


class _Shuffled:
    """A reader that yields its frames out of order (and so breaks the timestamp promise)."""

    def __init__(self, inner: Dataset) -> None:
        self._inner = inner
        for attr in ("name", "camera", "camera_right", "T_l_r", "T_b_c", "fps", "ground_truth"):
            setattr(self, attr, getattr(inner, attr))

    def __len__(self) -> int:
        return len(self._inner)

    def __iter__(self) -> Any:
        return iter(list(self._inner)[::-1])


def test_suite_fails_on_a_broken_reader() -> None:
    ds = REGISTRY.instantiate("dataset", {**default_node("synthetic"), **_synthetic(Path, Path())})
    broken = _Shuffled(ds)
    with pytest.raises(AssertionError):
        test_timestamps_strictly_increase((broken, list(broken)))  # type: ignore[arg-type]
    with pytest.raises(AssertionError):
        test_length_matches_iteration_and_indices((broken, list(broken)))  # type: ignore[arg-type]
