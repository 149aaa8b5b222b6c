"""After a monocular map merge moved the active map by a similarity of scale s (slamkit/pipeline/map_merging.py), the
tracker's motion model follows (``Tracker.map_moved``): the next frame is predicted by the velocity in the new scale
and tracked by the motion model at the pose the moved map gives it."""

from __future__ import annotations

import numpy as np

from slamkit.geometry.sim3 import Sim3
from slamkit.pipeline.map_merging import transform_map
from slamkit.pipeline.tracking import TrackingState
from slamkit.sensors import FrameData
from tests.unit.pipeline.test_monocular_initialization import CAMERA, N_POINTS, make_tracker, pose, view


def _track_after_a_merge(scale: float, tell_tracker: bool) -> tuple[str, np.ndarray]:
    """Frames 0-3 tracked, the map moved by a similarity of scale ``scale``, frame 4 tracked: (its method, its camera
    centre in the moved map's frame)."""
    rng = np.random.default_rng(3)
    xyz = rng.uniform([-3.0, -2.0, 3.0], [3.0, 2.0, 6.0], (N_POINTS, 3))
    desc = rng.integers(0, 256, (N_POINTS, 32), dtype=np.uint8)
    # frames 0-1 initialise (30 cm baseline); then the camera goes on at constant velocity
    xs = [0.0, 0.30, 0.36, 0.42, 0.48]
    records = {i: view(pose(x, 2.0 * i), xyz, desc, 0.3, rng) for i, x in enumerate(xs)}
    tracker = make_tracker(records)
    for i in range(4):
        out = tracker.step(FrameData(i, i / 30.0, np.zeros((1, 1), np.uint8)), CAMERA)
        assert out.state == TrackingState.OK or i == 0, out.message
    assert tracker.velocity is not None
    G = Sim3(scale, np.eye(3), MOVE_T)
    with tracker.store.write():
        transform_map(tracker.store, G)
    if tell_tracker:
        tracker.map_moved(G)
    out = tracker.step(FrameData(4, 4 / 30.0, np.zeros((1, 1), np.uint8)), CAMERA)
    assert out.T_c_w is not None
    return out.method, -out.T_c_w[:3, :3].T @ out.T_c_w[:3, 3]


MOVE_T = np.array([0.5, -0.2, 0.1])


def test_the_motion_model_follows_the_scale_of_a_merge() -> None:
    method, centre = _track_after_a_merge(0.5, tell_tracker=True)
    assert method == "motion_model"
    # without it the velocity, in the old scale, predicts too far and the motion model fails
    assert _track_after_a_merge(0.5, tell_tracker=False)[0] == "reference_keyframe"
    # the camera centre is where a rigid move (scale 1) puts it, scaled about the move's origin
    rigid_method, rigid_centre = _track_after_a_merge(1.0, tell_tracker=False)
    assert rigid_method == "motion_model"
    assert np.allclose(centre - MOVE_T, 0.5 * (rigid_centre - MOVE_T), atol=1e-3)


def test_a_frame_tracked_before_a_merge_and_recorded_after_it_follows_the_move() -> None:
    """The threaded runner records a frame after the step that tracked it; a merge moving the map in between must not
    mix the old frame of the pose with the new frame of the reference keyframe (a 5.9 m error on the long loop's
    merge): ``follow_map_moves`` moves the outcome's poses as the map moved, and the next frame tracks."""
    rng = np.random.default_rng(3)
    xyz = rng.uniform([-3.0, -2.0, 3.0], [3.0, 2.0, 6.0], (N_POINTS, 3))
    desc = rng.integers(0, 256, (N_POINTS, 32), dtype=np.uint8)
    xs = [0.0, 0.30, 0.36, 0.42, 0.48, 0.54]
    records = {i: view(pose(x, 2.0 * i), xyz, desc, 0.3, rng) for i, x in enumerate(xs)}
    tracker = make_tracker(records)
    outs = [tracker.step(FrameData(i, i / 30.0, np.zeros((1, 1), np.uint8)), CAMERA) for i in range(5)]
    out = outs[4]
    assert out.state == TrackingState.OK and out.T_c_w is not None and out.T_ref_w is not None
    assert out.map_moves == 0
    before_c = -out.T_c_w[:3, :3].T @ out.T_c_w[:3, 3]
    T_c_r = out.T_c_w @ np.linalg.inv(out.T_ref_w)
    G = Sim3(0.5, Sim3.exp(np.array([0.0, 0.3, 0.0, 0.0, 0.0, 0.0, 0.0])).R, MOVE_T)
    with tracker.store.write():  # what the loop-closing thread does while the runner has not recorded frame 4 yet
        transform_map(tracker.store, G)
        tracker.map_moved(G)
    with tracker.store.read():
        tracker.follow_map_moves(out)
    assert out.map_moves == 1
    after_c = -out.T_c_w[:3, :3].T @ out.T_c_w[:3, 3]
    assert np.allclose(after_c, G.act(before_c), atol=1e-9)
    # frame 4 became a keyframe (this test has no local mapping to insert it): it moved with the outcome
    assert [kf.id for kf in out.new_keyframes] == [out.reference_kf_id]
    assert np.allclose(out.T_ref_w, out.new_keyframes[0].T_c_w, atol=1e-12)
    assert np.allclose(out.new_keyframes[0].T_c_w, out.T_c_w, atol=1e-12)
    T_c_r_moved = out.T_c_w @ np.linalg.inv(out.T_ref_w)  # the relative pose, its translation in the new scale
    assert np.allclose(T_c_r_moved[:3, :3], T_c_r[:3, :3], atol=1e-9)
    assert np.allclose(T_c_r_moved[:3, 3], 0.5 * T_c_r[:3, 3], atol=1e-9)
    tracker.follow_map_moves(out)  # followed once only
    assert np.allclose(-out.T_c_w[:3, :3].T @ out.T_c_w[:3, 3], after_c, atol=1e-12)
    nxt = tracker.step(FrameData(5, 5 / 30.0, np.zeros((1, 1), np.uint8)), CAMERA)
    assert nxt.state == TrackingState.OK and nxt.method == "motion_model" and nxt.map_moves == 1
