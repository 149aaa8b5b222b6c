"""Monocular initialisation's reference-frame rules and initial map (ORB-SLAM2/3 Tracking::MonocularInitialization
and CreateInitialMapMonocular), on recorded observation records of a known scene: a reference frame needs more than
100 keypoints; a frame with fewer than 100 matches to it drops the reference and the *next* frame becomes the new
one; a two-view reconstruction builds the map with every triangulated point, bundle-adjusted without removing any
observation, at median depth 1."""

from __future__ import annotations

import numpy as np

from slamkit.features import Features, Observations
from slamkit.geometry import PinholeCamera
from slamkit.geometry.so3 import so3_exp
from slamkit.interfaces import FrontEnd
from slamkit.map.atlas import Atlas
from slamkit.map.store import InMemoryMapStore
from slamkit.pipeline.config import TrackingConfig
from slamkit.pipeline.tracking import Tracker, TrackingState
from slamkit.plugins import ComponentRegistry
from slamkit.sensors import FrameData

CAMERA = PinholeCamera(640, 480, 500.0, 500.0, 319.5, 239.5)
N_POINTS = 400


class RecordedFrontEnd:
    """Replays prepared observation records by frame index (the FrontEnd protocol's job without an image)."""

    uses_depth = False

    def __init__(self, records: dict[int, Observations]) -> None:
        self.records = records
        self.n_levels = 8
        self.scale_factor = 1.2

    def observe(self, data: FrameData, camera: object, initializing: bool = False) -> Observations:
        return self.records[data.index]

    def warm_up(self, camera: object) -> None:
        pass


def view(
    T_c_w: np.ndarray, xyz: np.ndarray, desc: np.ndarray, noise_px: float, rng: np.random.Generator
) -> Observations:
    """The record of the scene points a camera at T_c_w sees (level 0, angle 0), with pixel noise."""
    p_c = xyz @ T_c_w[:3, :3].T + T_c_w[:3, 3]
    uv = p_c[:, :2] / p_c[:, 2:] * 500.0 + np.array([319.5, 239.5])
    seen = np.flatnonzero((p_c[:, 2] > 0) & (uv[:, 0] > 20) & (uv[:, 0] < 620) & (uv[:, 1] > 20) & (uv[:, 1] < 460))
    px = (uv[seen] + rng.normal(0.0, noise_px, (seen.size, 2))).astype(np.float32)
    n = seen.size
    features = Features(
        px, px.copy(), np.zeros(n, np.int32), np.zeros(n, np.float32), np.ones(n, np.float32), desc[seen], 1.2, 8
    )
    bearing = np.c_[(px - np.array([319.5, 239.5])) / 500.0, np.ones(n)]
    return Observations.monocular(features, bearing / np.linalg.norm(bearing, axis=1, keepdims=True))


def pose(x: float, yaw_deg: float) -> np.ndarray:
    T_w_c = np.eye(4)
    T_w_c[:3, :3] = so3_exp(np.array([0.0, np.radians(yaw_deg), 0.0]))
    T_w_c[:3, 3] = [x, 0.0, 0.0]
    return np.linalg.inv(T_w_c)


def make_tracker(records: dict[int, Observations]) -> Tracker:
    registry = ComponentRegistry.discover()
    optimizer = registry.instantiate("optimizer", {"_target_": registry.get("optimizer", "scipy").spec.target})
    initializer = registry.instantiate("initializer", {"_target_": registry.get("initializer", "twoview").spec.target})
    frontend: FrontEnd = RecordedFrontEnd(records)
    return Tracker(
        TrackingConfig(), frontend, initializer, optimizer, Atlas.of(InMemoryMapStore()), np.random.default_rng(0)
    )


def test_reference_rules_and_initial_map() -> None:
    rng = np.random.default_rng(3)
    xyz = rng.uniform([-3.0, -2.0, 3.0], [3.0, 2.0, 6.0], (N_POINTS, 3))
    desc = rng.integers(0, 256, (N_POINTS, 32), dtype=np.uint8)
    other = rng.integers(0, 256, (N_POINTS, 32), dtype=np.uint8)  # a different scene: no descriptor matches
    records = {
        0: view(pose(0.0, 0.0), xyz[:80], desc[:80], 0.3, rng),  # 80 keypoints: not enough for a reference
        1: view(pose(0.0, 0.0), xyz, desc, 0.3, rng),  # becomes the reference
        2: view(pose(0.02, 0.2), xyz, other, 0.3, rng),  # no matches: the reference is dropped...
        3: view(pose(0.04, 0.4), xyz, desc, 0.3, rng),  # ...and this frame becomes the new one
        4: view(pose(0.30, 1.5), xyz, desc, 0.3, rng),  # 30 cm baseline at 3-6 m: initialises with frame 3
    }
    tracker = make_tracker(records)
    out = [tracker.step(FrameData(i, i / 30.0, np.zeros((1, 1), np.uint8)), CAMERA) for i in range(5)]
    assert "features" in out[0].message and tracker.state == TrackingState.OK
    assert out[1].message == "reference frame set"
    assert out[2].message.startswith("too few matches") and "reference reset" in out[2].message
    assert out[3].message == "reference frame set"
    assert out[4].state == TrackingState.OK and out[4].initialized_map, out[4].message
    kf_ini, kf_cur = out[4].new_keyframes
    assert (kf_ini.frame_index, kf_cur.frame_index) == (3, 4)
    store = tracker.store
    # every triangulated point is in the map with both observations (no outlier pass in the initial BA)
    assert store.n_points() > 0.9 * len(records[3])
    assert all(len(store.get_point(p).observations) == 2 for p in store.point_ids())
    assert kf_cur.n_tracked_points() == store.n_points()
    # median depth 1 in the first keyframe; the recovered motion is the true one up to that scale
    depths = np.array([store.get_point(p).xyz_w[2] for p in store.point_ids()])
    assert abs(np.median(depths) - 1.0) < 1e-6
    T_rel_true = pose(0.30, 1.5) @ np.linalg.inv(pose(0.04, 0.4))
    T_rel = store.get_keyframe(kf_cur.id).T_c_w
    t_true = T_rel_true[:3, 3] / np.linalg.norm(T_rel_true[:3, 3])
    assert np.degrees(np.arccos(np.clip(T_rel[:3, 3] @ t_true / np.linalg.norm(T_rel[:3, 3]), -1, 1))) < 2.0


class FlagRecordingFrontEnd(RecordedFrontEnd):
    """A RecordedFrontEnd that notes which frames asked for the initialisation extractor."""

    def __init__(self, records: dict[int, Observations]) -> None:
        super().__init__(records)
        self.initializing: dict[int, bool] = {}

    def observe(self, data: FrameData, camera: object, initializing: bool = False) -> Observations:
        self.initializing[data.index] = initializing
        return self.records[data.index]


def test_the_initialisation_extractor_stays_on_for_max_frames_after_initialising() -> None:
    """ORB-SLAM3 Tracking::GrabImageMonocular extracts with mpIniORBextractor until mMaxFrames frames after the map
    was initialised (``init_extractor_after_init``; mMaxFrames = the camera's fps, here 4 Hz); without it
    (ORB-SLAM2) the tracking extractor takes over on the first frame after the initialisation."""
    rng = np.random.default_rng(3)
    xyz = rng.uniform([-3.0, -2.0, 3.0], [3.0, 2.0, 6.0], (N_POINTS, 3))
    desc = rng.integers(0, 256, (N_POINTS, 32), dtype=np.uint8)
    records = {i: view(pose(0.3 * i, 1.5 * i), xyz, desc, 0.3, rng) for i in range(10)}  # initialises at frame 1
    registry = ComponentRegistry.discover()
    optimizer = registry.instantiate("optimizer", {"_target_": registry.get("optimizer", "scipy").spec.target})
    initializer = registry.instantiate("initializer", {"_target_": registry.get("initializer", "twoview").spec.target})
    for window, expected in ((True, {0, 1, 2, 3, 4, 5}), (False, {0, 1})):
        frontend = FlagRecordingFrontEnd(records)
        tracker = Tracker(
            TrackingConfig(init_extractor_after_init=window),
            frontend,
            initializer,
            optimizer,
            Atlas.of(InMemoryMapStore()),
            np.random.default_rng(0),
            fps=4.0,
        )
        out = [tracker.step(FrameData(i, i / 4.0, np.zeros((1, 1), np.uint8)), CAMERA) for i in range(10)]
        assert out[1].initialized_map, out[1].message
        assert {i for i, flag in frontend.initializing.items() if flag} == expected
