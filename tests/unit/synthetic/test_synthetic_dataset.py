"""SyntheticDataset as a Dataset: determinism, random access, skip/max_frames, fields, config and errors."""

from __future__ import annotations

import inspect
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hydra.utils import instantiate
from omegaconf import OmegaConf

from slamkit.errors import ConfigError
from slamkit.interfaces import Dataset
from slamkit.io.synthetic import SyntheticDataset

CONFIG = Path(__file__).resolve().parents[3] / "conf" / "dataset" / "synthetic.yaml"


def _frames_equal(a: SyntheticDataset, b: SyntheticDataset, i: int) -> bool:
    fa, fb = a[i], b[i]
    pairs: list[tuple[Any, Any]] = [
        (fa.image, fb.image),
        (fa.color, fb.color),
        (fa.image_right, fb.image_right),
        (fa.depth_m, fb.depth_m),
    ]
    pairs += [(fa.imu.acc_mps2, fb.imu.acc_mps2), (fa.imu.gyro_radps, fb.imu.gyro_radps)]
    return all(np.array_equal(x, y) for x, y in pairs if x is not None or y is not None)


def test_same_seed_gives_bit_identical_frames() -> None:
    opts: dict[str, Any] = {"scene": "twins", "color": True, "stereo": True, "seed": 7}
    a, b = SyntheticDataset(**opts), SyntheticDataset(**opts)
    for i in (0, 500, 1901):
        assert _frames_equal(a, b, i)


def test_different_seeds_give_different_textures_and_noise() -> None:
    a, b = SyntheticDataset(scene="room", seed=1), SyntheticDataset(scene="room", seed=2)
    fa, fb = a[0], b[0]
    np.testing.assert_array_equal(fa.T_w_c_gt, fb.T_w_c_gt)  # same world geometry and path
    np.testing.assert_array_equal(fa.depth_m, fb.depth_m)
    assert np.mean(np.abs(fa.image.astype(int) - fb.image.astype(int))) > 20  # different textures
    assert not np.array_equal(fa.imu.acc_mps2, fb.imu.acc_mps2)


def test_random_access_does_not_depend_on_order(synthetic: Callable[..., SyntheticDataset]) -> None:
    ds = synthetic(scene="room")
    first = ds[37].image.copy()
    ds[400], ds[3]
    np.testing.assert_array_equal(ds[37].image, first)
    fresh = SyntheticDataset(scene="room")
    np.testing.assert_array_equal(fresh[37].image, first)


def test_pixel_noise_is_seeded_and_configurable(synthetic: Callable[..., SyntheticDataset]) -> None:
    noisy, clean = synthetic(scene="room"), synthetic(scene="room", pixel_noise_std=0.0)
    diff = noisy[5].image.astype(np.float64) - clean[5].image
    assert 0.8 < diff.std() < 1.2  # default std 1 grey level (rounded, clipped)
    raw = clean.render_raw(5)
    np.testing.assert_array_equal(clean[5].image, raw.grey)  # noise-free frames are the exact render


def test_frame_fields_calibration_and_ground_truth(synthetic: Callable[..., SyntheticDataset]) -> None:
    ds = synthetic(scene="room", color=True, stereo=True)
    assert isinstance(ds, Dataset)
    assert ds.name == "synthetic/room" and ds.fps == 30.0
    assert len(ds) == 840  # 28 s at 30 Hz
    cam = ds.camera
    assert (cam.width, cam.height, cam.cx, cam.cy) == (640, 480, 319.5, 239.5)
    f = ds[123]
    assert f.index == 123 and f.timestamp_s == 123 / 30
    assert f.image.shape == (480, 640) and f.image.dtype == np.uint8
    assert f.color is not None and f.color.shape == (480, 640, 3)
    assert f.image_right is not None and f.image_right.shape == (480, 640)
    assert f.depth_m is not None and f.depth_m.dtype == np.float32 and f.depth_m.min() > 0
    assert f.T_w_c_gt is not None
    np.testing.assert_array_equal(f.T_w_c_gt, ds.ground_truth.T_w_c[123])
    assert ds.ground_truth.t_s[123] == f.timestamp_s
    assert ds.T_b_c is not None and len(f.imu) in (6, 7)  # 200 Hz between frames at 30 Hz


def test_skip_and_max_frames(synthetic: Callable[..., SyntheticDataset]) -> None:
    ds = synthetic(scene="room", skip=[50, 99], max_frames=80)
    assert len(ds) == 80
    assert ds.raw_indices()[49] == 49 and ds.raw_indices()[50] == 100 and ds.raw_indices()[-1] == 129
    f = ds[50]
    assert f.index == 50 and f.timestamp_s == 100 / 30
    np.testing.assert_array_equal(f.T_w_c_gt, ds.ground_truth.T_w_c[100])
    np.testing.assert_array_equal(f.image, synthetic(scene="room")[100].image)  # the same raw frame
    frames = list(ds)
    assert [fr.index for fr in frames] == list(range(80))
    assert [fr.timestamp_s for fr in frames] == [r / 30 for r in ds.raw_indices()]
    with pytest.raises(ConfigError, match=r"dataset\.skip"):
        SyntheticDataset(scene="room", skip=[5])


def test_options_modalities_off(synthetic: Callable[..., SyntheticDataset]) -> None:
    ds = synthetic(scene="planar", depth=False, imu=False, fx=450.0, fy=455.0, width=320, height=240)
    f = ds[0]
    assert f.depth_m is None and len(f.imu) == 0 and f.image.shape == (240, 320)
    assert ds.T_b_c is None and ds.imu_stream is None and ds.T_l_r is None
    assert (ds.camera.fx, ds.camera.fy, ds.camera.cx) == (450.0, 455.0, 159.5)


@pytest.mark.parametrize(
    ("options", "key"),
    [
        ({"scene": "kitchen"}, "dataset.scene"),
        ({"fps": 0}, "dataset.fps"),
        ({"duration_s": -1.0}, "dataset.duration_s"),
        ({"pixel_noise_std": -1.0}, "dataset.pixel_noise_std"),
        ({"stereo": True, "baseline_m": 0.0}, "dataset.baseline_m"),
        ({"imu_acc_noise_density": -1e-3}, "dataset.imu_acc_noise_density"),
        ({"imu_rate_hz": 0.0}, "dataset.imu_rate_hz"),
        ({"T_b_c": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}, "dataset.T_b_c"),
        ({"T_b_c": np.diag([1.0, 1.0, -1.0, 1.0]).tolist()}, "dataset.T_b_c"),
        ({"seed": 1.5}, "dataset.seed"),
        ({"texels_per_m": "dense"}, "dataset.texels_per_m"),
        ({"fx": -3.0}, "camera.fx"),
    ],
)
def test_bad_options_raise_config_errors_naming_the_key(options: dict[str, Any], key: str) -> None:
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        SyntheticDataset(**options)


def test_config_node_instantiates_with_the_top_level_seed() -> None:
    node = OmegaConf.load(CONFIG)
    assert node._target_ == "slamkit.io.synthetic.dataset.SyntheticDataset"
    # Every option in the node is a constructor parameter and vice versa (the node documents them all).
    params = set(inspect.signature(SyntheticDataset.__init__).parameters) - {"self"}
    assert set(node.keys()) - {"_target_"} == params
    cfg = OmegaConf.create({"seed": 11, "dataset": node})
    cfg.dataset.scene = "planar"
    cfg.dataset.skip = [2, 3]
    cfg.dataset.T_b_c = np.eye(4).tolist()
    ds = instantiate(cfg.dataset)
    assert isinstance(ds, SyntheticDataset)
    assert ds.seed == 11 and ds.scene.name == "planar" and len(ds) == 870 - 2
    np.testing.assert_array_equal(ds.T_b_c, np.eye(4))


def test_prepare_playback_builds_every_texture_up_front_and_changes_no_pixel() -> None:
    """Before a timed run the world is built whole: playing it then generates no texture, and the frames are the
    ones lazy generation gives."""
    lazy = SyntheticDataset(scene="planar", color=True, max_frames=40)
    prepared = SyntheticDataset(scene="planar", color=True, max_frames=40)
    prepared.prepare_playback()
    bank = prepared.renderer.bank
    n_planes = len(prepared.renderer.planes)
    assert len(bank._pyramids) == 2 * len(
        {(p.plane.texture, p.width_px, p.height_px) for p in prepared.renderer.planes}
    )
    before = dict(bank._pyramids)
    for i in (0, 20, 39):
        assert _frames_equal(lazy, prepared, i)
    assert bank._pyramids == before and n_planes > 0  # nothing generated while playing
