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
        tracker.map_moved(scale)
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
