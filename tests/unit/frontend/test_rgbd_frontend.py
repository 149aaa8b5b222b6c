"""frontend=rgbd (ORB-SLAM2 Frame::ComputeStereoFromRGBD): the registry builds it, the dataset reads depth for it,
each keypoint's depth is the depth map's at the raw keypoint and its virtual right coordinate u - bf / depth, the
close/far threshold is bf * ThDepth / fx, and a frame without a usable depth map is refused with the frame named."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from slamkit.config import compose_config
from slamkit.errors import DatasetError
from slamkit.frontend.rgbd import RgbdFrontEnd
from slamkit.interfaces import FrontEnd
from slamkit.plugins import ComponentRegistry


@pytest.fixture(scope="module")
def built() -> tuple[RgbdFrontEnd, object]:
    registry = ComponentRegistry.discover()
    cfg = compose_config(["frontend=rgbd", "dataset.max_frames=3"], registry=registry)
    from slamkit.app import build_components

    components = build_components(cfg, registry)
    frontend = registry.instantiate("frontend", cfg.frontend, extractor=components["features"], init_extractor=None)
    assert isinstance(frontend, RgbdFrontEnd) and isinstance(frontend, FrontEnd)
    assert registry.get("frontend", "rgbd").distribution.startswith("slamkit ")
    return frontend, components["dataset"]


def test_depth_and_virtual_right_coordinate_of_every_keypoint(built: tuple[RgbdFrontEnd, object]) -> None:
    frontend, dataset = built
    data = dataset[0]  # type: ignore[index]
    camera = dataset.camera  # type: ignore[attr-defined]
    assert data.depth_m is not None
    obs = frontend.observe(data, camera)
    assert len(obs) > 500
    u = obs.uv_px[:, 0].astype(int)
    v = obs.uv_px[:, 1].astype(int)
    expected = data.depth_m[v, u]
    has = expected > 0
    assert has.mean() > 0.95  # the synthetic room has depth everywhere it has texture
    np.testing.assert_array_equal(obs.depth_m[has], expected[has])
    assert np.all(np.isnan(obs.depth_m[~has])) and np.all(np.isnan(obs.u_right_px[~has]))
    np.testing.assert_allclose(
        obs.u_right_px[has], obs.uv_undist_px[has, 0] - frontend.bf / expected[has], rtol=0, atol=1e-3
    )
    assert obs.bf == frontend.bf == 40.0
    assert obs.th_depth_m == pytest.approx(40.0 * 40.0 / camera.K[0, 0])
    np.testing.assert_array_equal(obs.is_close(), has & (obs.depth_m < obs.th_depth_m))


def test_back_projection_lands_on_the_ground_truth(built: tuple[RgbdFrontEnd, object]) -> None:
    """Keypoints of frame 0 back-projected at their depth (UnprojectStereo) and projected into frame 2 with the
    ground-truth poses land where that frame's depth map says the surface is (exact synthetic depth)."""
    frontend, dataset = built
    d0, d2 = dataset[0], dataset[2]  # type: ignore[index]
    camera = dataset.camera  # type: ignore[attr-defined]
    obs = frontend.observe(d0, camera)
    idx = np.flatnonzero(np.isfinite(obs.depth_m))
    xyz_w = obs.unproject_stereo(idx, d0.T_w_c_gt, camera.K)
    T_c2_w = np.linalg.inv(d2.T_w_c_gt)
    p = xyz_w @ T_c2_w[:3, :3].T + T_c2_w[:3, 3]
    K = camera.K
    uv = np.stack([K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2], K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]], axis=1)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < 639) & (uv[:, 1] >= 0) & (uv[:, 1] < 479)
    ui, vi = np.round(uv[inside]).astype(int).T
    rel = np.abs(d2.depth_m[vi, ui] - p[inside, 2]) / p[inside, 2]
    assert np.median(rel) < 0.01


def test_a_missing_or_misregistered_depth_map_is_refused_naming_the_frame(built: tuple[RgbdFrontEnd, object]) -> None:
    frontend, dataset = built
    data = dataset[1]  # type: ignore[index]
    camera = dataset.camera  # type: ignore[attr-defined]
    with pytest.raises(DatasetError, match=r"frame 1 .*no depth map"):
        frontend.observe(dataclasses.replace(data, depth_m=None), camera)
    assert data.depth_m is not None
    with pytest.raises(DatasetError, match=r"frame 1 .*shape"):
        frontend.observe(dataclasses.replace(data, depth_m=data.depth_m[:-2]), camera)


def test_bf_and_th_depth_come_from_the_settings_file(built: tuple[RgbdFrontEnd, object]) -> None:
    """ORB-SLAM3's RGB-D settings (File.version 1.0: Stereo.b 0.08, Stereo.ThDepth 40) give bf = b x fx."""
    from pathlib import Path

    from slamkit.io.tum_rgbd import TumRgbdDataset

    root = Path("/work/shared/datasets/tum_rgbd/rgbd_dataset_freiburg1_xyz_first10")
    settings = Path("/work/shared/peers/configs/rgbd_TUM1.yaml")
    if not (root.is_dir() and settings.is_file()):
        pytest.skip("TUM fr1_xyz_first10 or the ORB-SLAM3 RGB-D settings not in /work/shared")
    frontend = RgbdFrontEnd(built[0].extractor, bf=12.0, th_depth=7.0)
    frontend.bind_dataset(TumRgbdDataset(root, settings=settings))
    assert frontend.bf == pytest.approx(0.08 * 517.306408) and frontend.th_depth == 40.0
    plain = RgbdFrontEnd(built[0].extractor, bf=12.0, th_depth=7.0)
    plain.bind_dataset(TumRgbdDataset(root))  # TUM's own calibration: no bf, the config's values stay
    assert plain.bf == 12.0 and plain.th_depth == 7.0
