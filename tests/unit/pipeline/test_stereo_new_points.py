"""Local mapping's new points between stereo/RGB-D keyframes as ORB-SLAM2/3's CreateNewMapPoints and
SearchForTriangulation: the stereo parallax that competes with the rays' is the new keyframe's (``if(bStereo1) ...
else if(bStereo2)``), and a stereo keypoint near the epipole is still a candidate (``if(!bStereo1 && !bStereo2)``)."""

from __future__ import annotations

import dataclasses

import numpy as np

from slamkit.features import Features, Observations
from slamkit.geometry.camera import PinholeCamera
from slamkit.map.atlas import Atlas
from slamkit.map.entities import KeyFrame
from slamkit.map.store import InMemoryMapStore
from slamkit.pipeline.config import LocalMappingConfig
from slamkit.pipeline.local_mapping import LocalMapper, _triangulate_with_depths

CAMERA = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)
BASELINE_M = 0.5
BF = BASELINE_M * 500.0


def stereo_keyframe(
    store: InMemoryMapStore, center_w: np.ndarray, xyz_w: np.ndarray, depth_m: np.ndarray | None, seed: int = 0
) -> KeyFrame:
    """A keyframe at ``center_w`` looking along +z (no rotation); keypoint j is point j's exact projection, with the
    right coordinate of ``depth_m[j]`` (NaN: no stereo match) or no depth at all (``depth_m`` None: monocular)."""
    T_c_w = np.eye(4)
    T_c_w[:3, 3] = -np.asarray(center_w, np.float64)
    cam = xyz_w @ T_c_w[:3, :3].T + T_c_w[:3, 3]
    uv = (cam[:, :2] / cam[:, 2:] * 500.0 + [320.0, 240.0]).astype(np.float32)
    n = len(xyz_w)
    desc = np.random.default_rng(seed).integers(0, 256, (n, 32), dtype=np.uint8)
    feats = Features(uv, uv, np.zeros(n, np.int32), np.zeros(n, np.float32), np.ones(n, np.float32), desc, 1.2, 8)
    obs = Observations.monocular(feats, CAMERA.unproject_image(uv.astype(np.float64)))
    if depth_m is not None:
        d = np.asarray(depth_m, np.float32)
        obs = dataclasses.replace(
            obs, u_right_px=(uv[:, 0] - BF / d).astype(np.float32), depth_m=d, bf=BF, th_depth_m=BASELINE_M * 35
        )
    kf_id = store.new_keyframe_id()
    return KeyFrame(kf_id, kf_id, float(kf_id), T_c_w, CAMERA, obs, np.full(n, -1, np.int64))


def test_the_new_keyframes_stereo_parallax_decides_between_rays_and_depth() -> None:
    """kf1 (the new keyframe) 20 m from the point, kf2 one metre closer: both have a depth, the rays' parallax is
    tiny. ORB-SLAM back-projects kf1's depth (kf2's stereo parallax is not even computed when kf1 has one), even where
    kf2's depth gives the larger stereo parallax; kf1's depth is 1% long here so the choice shows. Without kf1's depth,
    kf2's is used."""
    store = InMemoryMapStore()
    xyz = np.array([[0.5, 0.2, 20.0]])
    idx = np.zeros(1, np.int64)
    for kf2_depth_at_1, expect_z in ((True, 20.2), (False, 20.0)):
        kf1 = stereo_keyframe(store, np.zeros(3), xyz, np.array([20.2 if kf2_depth_at_1 else np.nan]))
        kf2 = stereo_keyframe(store, np.array([0.0, 0.0, 1.0]), xyz, np.array([19.0]))
        uv1 = kf1.features.uv_undist_px.astype(np.float64)
        uv2 = kf2.features.uv_undist_px.astype(np.float64)
        rays1 = np.c_[uv1, 1.0] @ np.linalg.inv(CAMERA.K).T
        rays2 = np.c_[uv2, 1.0] @ np.linalg.inv(CAMERA.K).T
        cos_par = np.sum(rays1 * rays2, axis=1) / np.linalg.norm(rays1, axis=1) / np.linalg.norm(rays2, axis=1)
        ok, got = _triangulate_with_depths(kf1, kf2, idx, idx, uv1, uv2, cos_par, 0.9998)
        assert ok[0]
        assert abs(got[0, 2] - expect_z) < 1e-3


def _mapper_with(kf1: KeyFrame, kf2: KeyFrame, store: InMemoryMapStore) -> LocalMapper:
    for kf in (kf2, kf1):
        store.add_keyframe(kf)
    return LocalMapper(LocalMappingConfig(), Atlas.of(store), None)  # type: ignore[arg-type]


def test_a_stereo_keypoint_near_the_epipole_is_a_triangulation_candidate() -> None:
    """Forward motion: kf1's centre projects to kf2's principal point (the epipole); a point straight ahead is
    matched there when either keypoint has a right coordinate (it can be made from its depth), not when neither has."""
    xyz = np.array([[0.05, 0.02, 10.0], [3.0, 1.5, 10.0]])
    for stereo in (True, False):
        store = InMemoryMapStore()
        depth1 = np.array([9.0, 9.0]) if stereo else None
        kf1 = stereo_keyframe(store, np.array([0.0, 0.0, 1.0]), xyz, depth1)
        kf2 = stereo_keyframe(store, np.zeros(3), xyz, None)
        mapper = _mapper_with(kf1, kf2, store)
        i1, _ = mapper._match_for_triangulation(kf1, kf2)
        assert (0 in i1.tolist()) is stereo, "near the epipole"
        assert 1 in i1.tolist(), "away from the epipole: a candidate either way"
