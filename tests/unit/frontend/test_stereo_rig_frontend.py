"""frontend=stereo_rig (ORB-SLAM3 non-rectified stereo, Frame::ComputeStereoFishEyeMatches + TriangulateMatches): on
a fisheye pair diverging by 15 degrees the triangulated points are the true ones and descriptor matches that break
the geometry are refused; on EuRoC V1_01's raw (distorted, unrectified) pair the depths agree with the rectified
front end's."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slamkit.features import Features
from slamkit.frontend.stereo_rig import rig_matches, rig_observations
from slamkit.geometry.camera import KannalaBrandtCamera
from slamkit.geometry.so3 import so3_exp

EUROC = Path("/work/shared/datasets/euroc/V1_01_easy")
SETTINGS = Path("/work/shared/datasets/calib/orb_slam2_examples/Stereo_EuRoC.yaml")


def _fisheye() -> KannalaBrandtCamera:
    # EuRoC-like fisheye intrinsics (ORB-SLAM3 Examples/Stereo/EuRoC.yaml's TUM-VI-style KB values, rounded)
    return KannalaBrandtCamera(640, 480, 280.0, 280.0, 320.0, 240.0, k=[-0.01, 0.05, -0.08, 0.04])


def _rig() -> np.ndarray:
    """T_c1_c2: camera 2 10 cm to the right of camera 1, turned 15 degrees outwards about y."""
    T = np.eye(4)
    T[:3, :3] = so3_exp(np.array([0.0, np.radians(15.0), 0.0]))
    T[:3, 3] = [0.10, 0.0, 0.0]
    return T


def _features(uv: np.ndarray, desc: np.ndarray, level: np.ndarray) -> Features:
    n = len(uv)
    return Features(
        uv_px=uv.astype(np.float32),
        uv_undist_px=uv.astype(np.float32),
        level=level.astype(np.int32),
        angle_deg=np.zeros(n, np.float32),
        response=np.ones(n, np.float32),
        descriptors=desc,
        scale_factor=1.2,
        n_levels=8,
    )


def _scene(seed: int = 0, noise_px: float = 0.3) -> tuple[Features, Features, np.ndarray, np.ndarray, np.ndarray]:
    """Points seen by both cameras, by camera 1 only, by camera 2 only -> (left, right, xyz_c1 (N1, 3) of each left
    keypoint (NaN when camera 2 does not see it), the true camera-2 index of each left keypoint (-1), T_c1_c2)."""
    rng = np.random.default_rng(seed)
    cam = _fisheye()
    T12 = _rig()
    T21 = np.linalg.inv(T12)
    xyz = rng.uniform([-5, -2.5, 0.8], [5, 2.5, 3.5], (600, 3))  # parallax above the 1.15 deg gate
    uv1, ok1 = cam.project_image(xyz)
    p2 = xyz @ T21[:3, :3].T + T21[:3, 3]
    uv2, ok2 = cam.project_image(p2)
    ok1 &= cam.in_image(uv1, 10)
    ok2 &= cam.in_image(uv2, 10)
    desc = rng.integers(0, 256, (600, 32), dtype=np.uint8)
    level = rng.integers(0, 4, 600)
    i1 = np.flatnonzero(ok1)
    i2 = np.flatnonzero(ok2)
    rng.shuffle(i2)
    noise1 = rng.normal(0, noise_px, (i1.size, 2))
    noise2 = rng.normal(0, noise_px, (i2.size, 2))
    desc2 = desc[i2].copy()
    flips = rng.integers(0, 32, (i2.size, 3))  # a few bits differ between the two images' descriptors
    for k in range(3):
        desc2[np.arange(i2.size), flips[:, k]] ^= np.uint8(1 << k)
    left = _features(uv1[i1] + noise1, desc[i1], level[i1])
    right = _features(uv2[i2] + noise2, desc2, level[i2])
    pos2 = {int(j): k for k, j in enumerate(i2)}
    truth_idx = np.array([pos2.get(int(j), -1) for j in i1])
    truth_xyz = np.where((truth_idx >= 0)[:, None], xyz[i1], np.nan)
    return left, right, truth_xyz, truth_idx, T12


@pytest.mark.parametrize("noise_px", [0.0, 0.3])
def test_fisheye_pair_triangulates_the_true_points(noise_px: float) -> None:
    left, right, truth_xyz, truth_idx, T12 = _scene(0, noise_px)
    cam = _fisheye()
    both = truth_idx >= 0
    assert both.sum() > 150 and (~both).sum() > 50  # an overlap and points seen by camera 1 only
    m = rig_matches(left, right, cam, cam, T12)
    found = m.left_to_right >= 0
    # the rays' parallax decides which pairs are triangulated (ORB-SLAM3: cos <= 0.9998, 1.15 deg)
    a = truth_xyz
    b = truth_xyz - T12[:3, 3]
    with np.errstate(invalid="ignore"):
        parallax = np.degrees(np.arccos(np.sum(a * b, axis=1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)))
    wide = both & (parallax > 1.3)
    assert wide.sum() > 150
    assert (found & wide).sum() > 0.95 * wide.sum()
    assert not (found & both & (parallax < 1.0)).any()
    assert np.array_equal(m.left_to_right[found], truth_idx[found])  # no wrong pair
    err = np.linalg.norm(m.xyz_c1[found] - truth_xyz[found], axis=1) / np.linalg.norm(truth_xyz[found], axis=1)
    if noise_px == 0.0:
        assert err.max() < 1e-5  # float32 keypoints
    else:  # depth error ~ z^2 / (baseline fx) x noise: about 3% at 3 m
        assert np.median(err) < 0.05 and err.max() < 0.2


def test_matches_breaking_the_geometry_are_refused() -> None:
    left, right, _, truth_idx, T12 = _scene(1)
    cam = _fisheye()
    # give 40 camera-1 keypoints the descriptor of a camera-2 keypoint far from their epipolar curve
    rng = np.random.default_rng(5)
    swapped = rng.choice(np.flatnonzero(truth_idx >= 0), 40, replace=False)
    partners = truth_idx[np.roll(swapped, 1)]
    desc = left.descriptors.copy()
    desc[swapped] = right.descriptors[partners]
    bad = _features(left.uv_px.astype(np.float64), desc, left.level)
    m = rig_matches(bad, right, cam, cam, T12)
    wrong = (m.left_to_right >= 0) & (m.left_to_right != truth_idx)
    assert wrong.sum() <= 1  # a swapped pair may by chance lie on the epipolar curve within the gate
    # the gates alone: a far larger reprojection gate lets the swapped pairs through
    loose = rig_matches(bad, right, cam, cam, T12, chi2_mono=1e9)
    assert ((loose.left_to_right >= 0) & (loose.left_to_right != truth_idx)).sum() > 10


def test_record_holds_both_cameras_keypoints() -> None:
    left, right, _, _, T12 = _scene(2)
    cam = _fisheye()
    obs = rig_observations(left, right, cam, cam, T12, th_depth=35.0)
    n1 = len(left)
    assert obs.two_cameras and obs.n_left == n1 and len(obs) == n1 + len(right)
    assert np.array_equal(obs.camera_index(), np.r_[np.zeros(n1), np.ones(len(right))])
    link = obs.stereo_match
    assert link is not None and obs.xyz_c1 is not None
    left_linked = np.flatnonzero(link[:n1] >= 0)
    assert np.array_equal(link[link[left_linked]], left_linked)  # links both ways
    np.testing.assert_allclose(obs.depth_m[left_linked], obs.xyz_c1[left_linked, 2], rtol=1e-6)
    assert np.isnan(obs.depth_m[n1:]).all() and np.isnan(obs.u_right_px).all()
    # bearings in each keypoint's own camera
    np.testing.assert_allclose(obs.bearing[n1:], cam.unproject_image(right.uv_undist_px.astype(np.float64)))
    assert obs.th_depth_m == pytest.approx(0.10 * 35.0)


@pytest.mark.skipif(not (EUROC / "mav0" / "cam1").is_dir(), reason="EuRoC V1_01 not in /work/shared")
def test_euroc_raw_pair_depths_agree_with_the_rectified_front_end() -> None:
    from slamkit.app import build_components
    from slamkit.config import compose_config
    from slamkit.plugins import ComponentRegistry

    def built(frontend: str, *extra: str) -> tuple[object, object]:
        registry = ComponentRegistry.discover()
        cfg = compose_config(
            [f"frontend={frontend}", "dataset=euroc", f"dataset.root={EUROC}", "dataset.stereo=true", *extra],
            registry=registry,
        )
        components = build_components(cfg, registry)
        fe = registry.instantiate("frontend", cfg.frontend, extractor=components["features"], init_extractor=None)
        fe.bind_dataset(components["dataset"])
        return fe, components["dataset"]

    raw_fe, raw = built("stereo_rig")
    rect_fe, rect = built("stereo", f"dataset.settings={SETTINGS}")
    d_raw = raw[0]  # type: ignore[index]
    obs = raw_fe.observe(d_raw, raw.camera)  # type: ignore[attr-defined]
    assert obs.stereo_match is not None and obs.xyz_c1 is not None
    matched = np.flatnonzero(obs.stereo_match[: obs.n_left] >= 0)
    assert matched.size > 150  # 220 (ORB-SLAM3 parallax gate: 1.15 deg is 5.5 m at 11 cm)
    ref = rect_fe.observe(rect[0], rect.camera)  # type: ignore[attr-defined]
    z_raw = np.median(obs.depth_m[matched])
    z_rect = np.nanmedian(ref.depth_m)
    assert abs(z_raw - z_rect) / z_rect < 0.1  # measured 2.115 m against 2.103 m


@pytest.mark.slow
def test_rendered_fisheye_pair_gives_the_rendered_depths() -> None:
    """The synthetic room through a Kannala-Brandt pair whose right camera diverges by 15 degrees (rendered wide and
    remapped): the triangulated depths of the stereo matches are the rendered ones within the disparity noise."""
    from slamkit.app import build_components
    from slamkit.config import compose_config
    from slamkit.plugins import ComponentRegistry

    registry = ComponentRegistry.discover()
    cfg = compose_config(
        [
            "frontend=stereo_rig",
            "dataset.stereo=true",
            "dataset.camera_model=kannala_brandt",
            "dataset.fx=300",
            "dataset.fy=300",
            "dataset.kb_k=[0.0,0.0,0.0,0.0]",
            "dataset.stereo_yaw_deg=15",
            "dataset.max_frames=2",
            "dataset.imu=false",
        ],
        registry=registry,
    )
    components = build_components(cfg, registry)
    fe = registry.instantiate("frontend", cfg.frontend, extractor=components["features"], init_extractor=None)
    dataset = components["dataset"]
    fe.bind_dataset(dataset)
    assert dataset.camera.model == "kannala_brandt"  # type: ignore[attr-defined]
    data = dataset[1]  # type: ignore[index]
    obs = fe.observe(data, dataset.camera)  # type: ignore[attr-defined]
    assert obs.stereo_match is not None
    n1 = obs.n_left
    matched = np.flatnonzero(obs.stereo_match[:n1] >= 0)
    assert matched.size > 200  # 303 measured of 1000 keypoints
    uv = np.round(obs.uv_px[matched]).astype(int)
    truth = data.depth_m[uv[:, 1], uv[:, 0]]
    err = (obs.depth_m[matched] - truth) / truth
    # disparity noise: z / (baseline fx) ~ 8% of the depth per px at 3 m
    assert np.median(np.abs(err)) < 0.08 and abs(np.median(err)) < 0.03
