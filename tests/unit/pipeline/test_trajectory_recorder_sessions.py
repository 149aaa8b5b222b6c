"""Frames across sessions (docs/atlas.md, "Multi-session"): a recorder's frames as a map file keeps them
(``TrajectoryRecorder.export``: culled reference keyframes resolved to surviving ones, ORB-SLAM SaveTrajectoryTUM),
read back into a later session's recorder (``load``) and placed against the keyframes as that session leaves them;
a runner's ``KeptFrames`` keeps the frames of maps its recorder does not hold (loaded, left, absorbed)."""

from __future__ import annotations

import numpy as np

from slamkit.map.atlas import MapChange
from slamkit.pipeline.outcomes import CulledKeyFrame
from slamkit.pipeline.trajectory import KeptFrames, TrajectoryRecorder
from slamkit.sensors import FrameRecords


def _T(x: float, yaw: float = 0.0) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[0, 3] = x
    return T


def _session() -> tuple[TrajectoryRecorder, dict[int, np.ndarray]]:
    """Keyframes 1 (kept) and 2 (culled, child of 1) and 3 (culled, child of 2); a frame on each."""
    poses = {1: _T(0.0), 2: _T(-1.0, 0.3), 3: _T(-2.0, -0.2)}  # T_c_w
    rec = TrajectoryRecorder()
    for i, (kf, t) in enumerate([(1, 0.0), (2, 1.0), (3, 2.0)]):
        rec.record(i, t, _T(-0.1 - kf, 0.05 * kf), kf, poses[kf])
    inv = np.linalg.inv
    rec.on_culled(CulledKeyFrame(3, 2, poses[3] @ inv(poses[2]), poses[3]))
    rec.on_culled(CulledKeyFrame(2, 1, poses[2] @ inv(poses[1]), poses[2]))
    return rec, poses


def test_export_resolves_culled_references_to_the_same_poses() -> None:
    rec, poses = _session()
    exported = rec.export([1])
    assert exported.ref_kf_id.tolist() == [1, 1, 1] and exported.frame_index.tolist() == [0, 1, 2]
    # a later session moved keyframe 1: the exported frames follow it exactly as the recorder's own frames do
    moved = {1: _T(0.5, 0.1)}
    later = TrajectoryRecorder()
    later.load(exported)
    np.testing.assert_allclose(later.frames_at(moved).T_w_c, rec.frames_at(moved).T_w_c, atol=1e-12)
    # at the poses of the session itself: where it tracked the frames
    np.testing.assert_allclose(
        later.frames_at({1: poses[1]}).T_w_c, [np.linalg.inv(_T(-0.1 - k, 0.05 * k)) for k in (1, 2, 3)], atol=1e-12
    )
    # a frame that resolves to no keyframe of the map is left out
    assert len(rec.export([7])) == 0


def test_loaded_frames_join_in_time_order_and_can_be_left_out() -> None:
    rec, _ = _session()
    later = TrajectoryRecorder()
    later.record_relative(10, 5.0, 1, _T(-3.0))
    later.load(rec.export([1]))
    traj = later.frames_at({1: np.eye(4)})
    assert traj.t_s.tolist() == [0.0, 1.0, 2.0, 5.0]
    assert later.frames_at({1: np.eye(4)}, loaded=False).t_s.tolist() == [5.0]
    # a session whose times overlap the loaded ones (the same ground again): its frames come out in time order
    later.record_relative(11, 0.5, 1, _T(-3.5))
    assert later.frames_at({1: np.eye(4)}).t_s.tolist() == [0.0, 0.5, 1.0, 2.0, 5.0]
    # exported again (a third session's map file): every frame, loaded ones included
    assert sorted(later.export([1]).t_s.tolist()) == [0.0, 0.5, 1.0, 2.0, 5.0]


def test_kept_frames_follow_new_maps_merges_and_resets() -> None:
    loaded = FrameRecords(np.array([0.0, 1.0]), np.array([0, 1]), np.array([1, 1]), np.stack([_T(-0.1), _T(-0.2)]))
    kept = KeptFrames({0: loaded})
    recorder = TrajectoryRecorder()
    # the session starts a new map (1) after a frame in the loaded map 0
    recorder.record_relative(0, 2.0, 1, _T(-0.3))
    kept.map_changed(MapChange.NEW_MAP, 0, recorder)
    assert len(recorder) == 0
    recorder.record_relative(1, 3.0, 20, _T(-0.4))
    out = kept.export({0: [1], 1: [20]}, 1, recorder)
    assert out[0].t_s.tolist() == [0.0, 1.0, 2.0] and out[1].t_s.tolist() == [3.0]
    # the active map 1 (keyframe 20) moves by a similarity of scale 2 and absorbs map 0: its frames are rescaled
    recorder.rescale([20], 2.0)
    kept.merged(1, 0, [20], 2.0)
    out = kept.export({1: [1, 20]}, 1, recorder)
    assert out[1].t_s.tolist() == [0.0, 1.0, 2.0, 3.0]
    np.testing.assert_allclose(out[1].T_c_r[:, 0, 3], [-0.1, -0.2, -0.3, -0.8])
    # a keyframe of the merged map culled: the loaded frames on it resolve to its parent
    kept.on_culled(1, CulledKeyFrame(1, 20, _T(5.0), _T(0.0)))
    np.testing.assert_allclose(kept.export({1: [20]}, 1, recorder)[1].T_c_r[:3, 0, 3], [4.9, 4.8, 4.7])
    # the active map reset: its frames are gone
    kept.map_changed(MapChange.RESET, 1, recorder)
    assert len(recorder) == 0 and len(kept.export({2: []}, 2, recorder)[2]) == 0
