"""A merge's recorders (slamkit/eval/run_record.py on MapsMerged): the active map's recorder takes over the absorbed
map's frames, rescaled ones first; the frames come out in time order (a trajectory file's timestamps must not
decrease; the long-loop kidnap run wrote the absorbed map's earlier frames after the active map's)."""

from __future__ import annotations

import numpy as np

from slamkit.pipeline.trajectory import TrajectoryRecorder


def _T(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def test_absorbed_frames_come_out_in_time_order_and_rescaled_ones_keep_their_keyframe() -> None:
    into, absorbed = TrajectoryRecorder(), TrajectoryRecorder()
    # the active map (keyframe 10 at x = 0) tracked frames at 30-31 s; the absorbed map (keyframe 1) at 0-1 s
    for i, t in enumerate([30.0, 30.5, 31.0]):
        into.record_relative(100 + i, t, 10, _T(-0.1 * i))  # T_c_r: the camera 0.1 m per frame along x
    for i, t in enumerate([0.0, 0.5, 1.0]):
        absorbed.record_relative(i, t, 1, _T(-0.2 * i))
    into.rescale(None, 0.5)  # the active map moved by a similarity of scale 0.5
    into.absorb(absorbed)
    traj = into.frames_at({10: np.eye(4), 1: _T(-5.0)})
    assert traj.t_s.tolist() == [0.0, 0.5, 1.0, 30.0, 30.5, 31.0]
    np.testing.assert_allclose(traj.T_w_c[:, 0, 3], [5.0, 5.2, 5.4, 0.0, 0.05, 0.1])
