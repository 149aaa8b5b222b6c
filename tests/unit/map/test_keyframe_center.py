"""KeyFrame.center_w, computed once per pose array: the centre -R^T t of the current pose, recomputed when the store
replaces the pose, and a new array each call (a caller writing into it changes nothing)."""

from __future__ import annotations

import numpy as np

from slamkit.map.entities import KeyFrame, replace_fields


def _pose(angle: float, t: tuple[float, float, float]) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    T = np.eye(4)
    T[:3, :3] = [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]
    T[:3, 3] = t
    return T


def _keyframe(T: np.ndarray) -> KeyFrame:
    """A keyframe with its pose only (the centre reads nothing else)."""
    return KeyFrame(0, 0, 0.0, T, None, None, np.zeros(0, np.int64))  # type: ignore[arg-type]


def test_center_is_that_of_the_current_pose_and_a_fresh_array() -> None:
    T1 = _pose(0.3, (0.1, -0.2, 0.5))
    kf = _keyframe(T1)
    want1 = -T1[:3, :3].T @ T1[:3, 3]
    c = kf.center_w
    assert np.array_equal(c, want1)
    c[:] = 99.0  # the caller's own array
    assert np.array_equal(kf.center_w, want1)
    assert kf.center_w is not kf.center_w
    T2 = _pose(-0.7, (1.0, 2.0, -3.0))
    replace_fields(kf, T_c_w=np.array(T2))  # how the store sets a new pose (a new array)
    assert np.array_equal(kf.center_w, -T2[:3, :3].T @ T2[:3, 3])
    replace_fields(kf, T_c_w=np.array(T1))
    assert np.array_equal(kf.center_w, want1)
