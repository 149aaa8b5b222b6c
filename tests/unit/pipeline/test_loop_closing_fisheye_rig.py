"""Loop closing's Sim3 with a fisheye rig (ORB-SLAM3 LoopClosing with a KannalaBrandt8 pair): the Sim3 RANSAC, the
guided matching and the Sim3 optimisation project through each keyframe's own camera model (Sim3Solver and
OptimizeSim3: mpCamera->project; SearchByProjection(Scw): pKF->mpCamera->project) and work on camera 1's keypoints
(get<0> of GetIndexInKeyFrame; the left grid of GetFeaturesInArea).

The world: a textured wall seen at up to ~50 degrees off the axis by a Kannala-Brandt camera (fx = 300), where a
pinhole projection is off by hundreds of pixels. A third of the wall's points are recorded at camera-2 keypoints
placed at exactly the pixel camera 1 would see them at, with the point's descriptor: a search that looked among camera
2's keypoints with camera 1's projection would match them."""

from __future__ import annotations

import numpy as np
import pytest
from omegaconf import OmegaConf

from slamkit.config import compose_config
from slamkit.features import Observations
from slamkit.geometry.camera import KannalaBrandtCamera
from slamkit.geometry.se3 import invert_T
from slamkit.geometry.sim3 import Sim3
from slamkit.geometry.sim3_ransac import ransac_sim3
from slamkit.geometry.so3 import so3_exp
from slamkit.map.atlas import Atlas
from slamkit.map.entities import KeyFrame, MapPoint
from slamkit.map.store import InMemoryMapStore
from slamkit.optim.factory import build_optimizer
from slamkit.pipeline.config import PipelineConfig
from slamkit.pipeline.loop_closing import LoopCloser
from slamkit.pipeline.loop_verification import loop_window, project_window
from slamkit.pipeline.map_points import update_normal_and_depth
from slamkit.plugins import ComponentRegistry

F64 = np.ndarray

CAMERA = KannalaBrandtCamera(640, 480, 300.0, 300.0, 320.0, 240.0, [0.02, -0.01, 0.0, 0.0])
N_POINTS = 360
#: the current side's map drifted from the true world: turned 3 degrees about the vertical, moved 0.7 m
DRIFT = np.eye(4)
DRIFT[:3, :3] = so3_exp(np.array([0.0, 0.0, np.radians(3.0)]))
DRIFT[:3, 3] = [0.5, -0.4, 0.3]


def pose_at(x: float, y: float = 0.0) -> F64:
    """T_c_w of a camera at (x, y, 0) looking along +y (world z up, camera y down)."""
    T_w_c = np.eye(4)
    T_w_c[:3, :3] = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    T_w_c[:3, 3] = [x, y, 0.0]
    return invert_T(T_w_c)


def _record(uv: F64, desc: np.ndarray, n_left: int) -> Observations:
    """A two-camera record: keypoints [0, n_left) of camera 1, the rest of camera 2 (no stereo matches)."""
    n = len(uv)
    T_c2_c1 = np.eye(4)
    T_c2_c1[:3, :3] = so3_exp(np.array([0.0, np.radians(15.0), 0.0]))
    T_c2_c1[0, 3] = -0.1
    bearing = np.full((n, 3), np.nan)
    bearing[:n_left] = CAMERA.unproject_image(uv[:n_left])
    bearing[n_left:] = CAMERA.unproject_image(uv[n_left:])
    return Observations(
        uv_px=uv.astype(np.float32),
        uv_undist_px=uv.astype(np.float32),
        level=np.zeros(n, np.int32),
        angle_deg=np.zeros(n, np.float32),
        response=np.ones(n, np.float32),
        descriptors=desc,
        scale_factor=1.2,
        n_levels=8,
        bearing=bearing,
        u_right_px=np.full(n, np.nan, np.float32),
        depth_m=np.full(n, np.nan, np.float32),
        bf=30.0,  # 0.1 m x fx: metric scale (fix_scale)
        th_depth_m=3.5,
        sensor="stereo",
        n_left=n_left,
        stereo_match=np.full(n, -1, np.int64),
        xyz_c1=np.full((n, 3), np.nan),
        camera_2=CAMERA,
        T_c2_c1=T_c2_c1,
    )


class RigWorld:
    """Points on the plane y = 4 m over +-5 m x +-3 m; the loop's side (three keyframes, true world) and the current
    side (three keyframes in a map drifted by DRIFT), each with its own points. A keyframe sees point i at a camera-1
    keypoint when i % 3 != 0, else only at a camera-2 keypoint (at camera 1's pixel: the trap)."""

    def __init__(self, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        self.xyz = np.column_stack(
            [rng.uniform(-5.0, 5.0, N_POINTS), np.full(N_POINTS, 4.0), rng.uniform(-3.0, 3.0, N_POINTS)]
        )
        self.desc = rng.integers(0, 256, (N_POINTS, 32), dtype=np.uint8)
        self.store = InMemoryMapStore()
        self.loop_ids, self.loop_pids = self.add_group([pose_at(x) for x in (0.0, 0.2, -0.2)], np.eye(4))
        self.cur_ids, self.cur_pids = self.add_group([pose_at(x, 0.3) for x in (0.05, 0.25, -0.15)], DRIFT)
        #: feature index -> point index (the wall's), per keyframe
        self.point_of: dict[int, np.ndarray] = {}

    def add_group(self, T_true: list[F64], drift: F64) -> tuple[list[int], list[int]]:
        store = self.store
        pids = [store.new_point_id() for _ in range(N_POINTS)]
        kf_ids: list[int] = []
        obs: list[tuple[int, np.ndarray]] = []
        for T in T_true:
            uv, ok = CAMERA.project_image(self.xyz @ T[:3, :3].T + T[:3, 3])
            ok &= CAMERA.in_image(np.where(np.isfinite(uv), uv, -1.0), 5.0)
            idx = np.arange(N_POINTS)
            first = idx[ok & (idx % 3 != 0)]
            second = idx[ok & (idx % 3 == 0)]
            order = np.concatenate([first, second])
            feats = _record(uv[order], self.desc[order].copy(), len(first))
            kf = KeyFrame(
                store.new_keyframe_id(), len(kf_ids), 0.0, T @ invert_T(drift), CAMERA, feats, np.full(len(order), -1)
            )
            store.add_keyframe(kf)
            kf_ids.append(kf.id)
            obs.append((kf.id, order))
        xyz_map = self.xyz @ drift[:3, :3].T + drift[:3, 3]
        for i, pid in enumerate(pids):
            store.add_point(MapPoint(pid, xyz_map[i].copy(), self.desc[i].copy(), kf_ids[0], kf_ids[0]))
        for k, order in obs:
            for f, i in enumerate(order):
                store.add_observation(pids[int(i)], k, f)
        keyframes = {k: store.get_keyframe(k) for k in kf_ids}
        for pid in pids:
            update_normal_and_depth(store, store.get_point(pid), keyframes)
        for k in kf_ids:
            store.update_connections(k)
        return kf_ids, pids


@pytest.fixture(scope="module")
def world() -> RigWorld:
    return RigWorld()


def _wall_index(world: RigWorld, kf: KeyFrame, f: int) -> int:
    pid = int(kf.point_ids[f])
    return (world.cur_pids if pid in set(world.cur_pids) else world.loop_pids).index(pid)


def test_guided_matching_projects_through_the_fisheye_model_into_camera_1_only(world: RigWorld) -> None:
    current = world.store.get_keyframe(world.cur_ids[0])
    window = loop_window(world.store, world.loop_ids[0])
    # the hypothesis: the current camera's true pose in the loop side's (true) world
    proj = project_window(world.store, current, Sim3.from_se3(pose_at(0.05, 0.3)), window, 3.0, 50)
    n_left = current.features.n_left
    assert len(proj.matches) >= 0.95 * n_left  # the wall's camera-1 keypoints, out to ~50 degrees off the axis
    assert all(f < n_left for f in proj.matches)  # never the camera-2 keypoints at the same pixels
    assert all(world.loop_pids.index(pid) == _wall_index(world, current, f) for f, pid in proj.matches.items())


def _loop_closer(world: RigWorld) -> LoopCloser:
    cfg = compose_config()
    registry = ComponentRegistry.discover()
    pipeline = PipelineConfig.from_node(OmegaConf.to_container(cfg.pipeline, resolve=True))  # type: ignore[arg-type]
    place = registry.instantiate("place", cfg.place)
    for k in world.store.keyframe_ids():
        world.store.set_keyframe_bow(k, place.transform(world.store.get_keyframe(k).features.descriptors))
    optimizer = build_optimizer(cfg.optimizer, registry)
    return LoopCloser(pipeline.loop_closing, Atlas.of(world.store), optimizer, place, np.random.default_rng(0))


def test_the_common_region_of_a_fisheye_rig_recovers_the_drift(world: RigWorld) -> None:
    """ORB-SLAM3 DetectCommonRegionsFromBoW on Kannala-Brandt keyframes: BoW matches, Sim3 RANSAC, guided matching,
    Sim3 optimisation (fixed scale: a rig) and refined matching give the current keyframe's true pose."""
    closer = _loop_closer(world)
    current = world.store.get_keyframe(world.cur_ids[0])
    info: dict[str, object] = {}
    hyp = closer._common_region(current, world.loop_ids[0], info)
    assert hyp is not None, info
    T_true = pose_at(0.05, 0.3)
    S = hyp.S_cw.matrix()
    assert hyp.S_cw.s == pytest.approx(1.0, abs=1e-9)  # SE(3) for a rig
    R_err = S[:3, :3].T @ T_true[:3, :3]
    assert np.degrees(np.arccos(np.clip((np.trace(R_err) - 1) / 2, -1, 1))) < 0.05
    assert np.linalg.norm(S[:3, 3] - T_true[:3, 3]) < 0.005
    n_left = current.features.n_left
    assert len(hyp.matches) >= 0.95 * n_left and all(f < n_left for f in hyp.matches)
    assert int(info["optimized_inliers"]) >= 0.95 * int(info["projected_matches"])  # type: ignore[call-overload]


def test_sim3_ransac_projects_through_each_camera() -> None:
    rng = np.random.default_rng(5)
    n = 200
    xyz2 = np.column_stack([rng.uniform(-5, 5, n), rng.uniform(-3, 3, n), np.full(n, 4.0)])  # up to ~50 deg
    S_12 = Sim3(1.0, so3_exp(np.array([0.02, -0.05, 0.01])), np.array([0.2, -0.1, 0.1]))
    xyz1 = S_12.act(xyz2)
    uv1 = CAMERA.project_image(xyz1)[0] + rng.normal(0, 0.5, (n, 2))
    uv2 = CAMERA.project_image(xyz2)[0] + rng.normal(0, 0.5, (n, 2))
    sig = np.ones(n)
    fish = ransac_sim3(
        xyz1,
        xyz2,
        uv1,
        uv2,
        CAMERA.K,
        CAMERA.K,
        sig,
        sig,
        np.random.default_rng(1),
        fix_scale=True,
        project1=CAMERA.project_image,
        project2=CAMERA.project_image,
    )
    assert fish.S_12 is not None and fish.inliers.mean() > 0.95
    assert np.linalg.norm(fish.S_12.t - S_12.t) < 0.01
    # the pinhole K on raw fisheye pixels: only the points near the axis fit
    pinhole = ransac_sim3(xyz1, xyz2, uv1, uv2, CAMERA.K, CAMERA.K, sig, sig, np.random.default_rng(1), fix_scale=True)
    assert pinhole.inliers.mean() < 0.5
