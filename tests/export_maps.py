"""Hand-made maps with exact geometry for the map-export tests (tests/unit/export): keyframes whose features are
the exact projections of the points, and a FrameImages source whose pixels encode their coordinates."""

from __future__ import annotations

from collections.abc import Iterable, Iterator

import numpy as np

from slamkit.features import Features, Observations
from slamkit.geometry.camera import KannalaBrandtCamera, PinholeCamera
from slamkit.interfaces import Camera
from slamkit.map.entities import KeyFrame, MapPoint
from slamkit.map.store import InMemoryMapStore

PINHOLE = PinholeCamera(640, 480, 500.0, 490.0, 319.5, 239.5)
DISTORTED = PinholeCamera(640, 480, 500.0, 490.0, 321.0, 238.0, dist=(-0.28, 0.07, 0.001, -0.0005))
DISTORTED_K3 = PinholeCamera(640, 480, 500.0, 490.0, 321.0, 238.0, dist=(-0.28, 0.07, 0.001, -0.0005, 0.01))
FISHEYE = KannalaBrandtCamera(752, 480, 190.0, 191.0, 376.0, 240.0, k=(0.01, -0.02, 0.003, -0.001))


def _pose_c_w(yaw: float, center_w: np.ndarray) -> np.ndarray:
    """T_c_w of a camera at center_w turned by yaw about the world y axis (z forward)."""
    c, s = np.cos(yaw), np.sin(yaw)
    R_w_c = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    T = np.eye(4)
    T[:3, :3] = R_w_c.T
    T[:3, 3] = -R_w_c.T @ center_w
    return T


class StripeImages:
    """FrameImages whose pixel (u, v) of frame f is RGB (u % 256, v % 256, 10 f % 256)."""

    def __init__(self, width: int, height: int) -> None:
        self.width, self.height = width, height

    def rgb(self, frame_index: int) -> np.ndarray:
        v, u = np.mgrid[0 : self.height, 0 : self.width]
        return np.stack([u % 256, v % 256, np.full_like(u, (10 * frame_index) % 256)], axis=2).astype(np.uint8)

    def frames(self, frame_indices: Iterable[int]) -> Iterator[tuple[int, np.ndarray]]:
        for i in sorted(set(frame_indices)):
            yield i, self.rgb(i)


def build_map(camera: Camera, store: InMemoryMapStore, n_points: int = 60, seed: int = 0, frame0: int = 0) -> None:
    """Three keyframes looking at n_points random points 4-6 m ahead; each keyframe's features: the exact raw
    projections of the points it sees (plus two features observing nothing)."""
    rng = np.random.default_rng(seed)
    xyz = np.column_stack(
        [rng.uniform(-1.5, 1.5, n_points), rng.uniform(-1.0, 1.0, n_points), rng.uniform(4, 6, n_points)]
    )
    poses = [_pose_c_w(0.05 * k, np.array([0.2 * k, 0.01 * k, 0.0])) for k in range(3)]
    pids = [store.new_point_id() for _ in range(n_points)]
    kf_ids = []
    for k, T_c_w in enumerate(poses):
        xyz_c = xyz @ T_c_w[:3, :3].T + T_c_w[:3, 3]
        uv = np.asarray(camera.project(xyz_c), np.float64)
        uv = np.vstack([uv, [[10.0, 12.0], [30.0, 40.0]]]).astype(np.float32)
        n = uv.shape[0]
        feats = Features(
            uv_px=uv,
            uv_undist_px=uv,
            level=np.zeros(n, np.int32),
            angle_deg=np.zeros(n, np.float32),
            response=np.zeros(n, np.float32),
            descriptors=np.zeros((n, 32), np.uint8),
            scale_factor=1.2,
            n_levels=8,
        )
        obs = Observations.monocular(feats, np.tile([0.0, 0.0, 1.0], (n, 1)))
        kf_id = store.new_keyframe_id()
        store.add_keyframe(KeyFrame(kf_id, frame0 + 3 * k, (frame0 + 3 * k) / 30.0, T_c_w, camera, obs, np.full(n, -1)))
        kf_ids.append(kf_id)
    for i, pid in enumerate(pids):
        store.add_point(MapPoint(pid, xyz[i], np.zeros(32, np.uint8), kf_ids[0], kf_ids[0]))
        for k, kf_id in enumerate(kf_ids):
            if k == 2 and i % 3 == 0:  # a third of the points unseen by the last keyframe
                continue
            store.add_observation(pid, kf_id, i)
