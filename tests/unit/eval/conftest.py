"""Fixtures for the slamkit.eval tests: synthetic trajectories with known geometry."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slamkit.sensors import Trajectory

MakeTrajectory = Callable[..., Trajectory]


def _make_trajectory(n: int = 50, seed: int = 0, t0_s: float = 1000.0, dt_s: float = 0.1) -> Trajectory:
    """A smooth 3D camera path (a loop with height changes) with orientations that vary, n poses."""
    rng = np.random.default_rng(seed)
    u = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    xyz = np.stack([3.0 * np.cos(u), 2.0 * np.sin(u), 0.5 * np.sin(2.0 * u)], axis=1)
    xyz += rng.normal(scale=0.01, size=xyz.shape)
    rotvecs = np.stack([0.2 * np.sin(u), 0.1 * np.cos(3.0 * u), u], axis=1)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(rotvecs).as_matrix()
    T[:, :3, 3] = xyz
    return Trajectory(t0_s + dt_s * np.arange(n, dtype=np.float64), T)


@pytest.fixture
def make_trajectory() -> MakeTrajectory:
    """Factory: make_trajectory(n=50, seed=0, t0_s=1000.0, dt_s=0.1) -> Trajectory."""
    return _make_trajectory
