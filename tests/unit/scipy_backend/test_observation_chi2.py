"""slamkit_scipy.bundle.observation_chi2's compiled pinhole path (kernels.ba_chi2_depth) against the numpy formulas of
slamkit_scipy.reprojection, to the bit: the local BA's outlier decisions (chi2 against the gate, depth > 0) and so the
trajectory depend on it."""

from __future__ import annotations

import numpy as np
import pytest
from slamkit_scipy.bundle import BAState, _camera_points, observation_chi2
from slamkit_scipy.lie import se3_exp_batch
from slamkit_scipy.reprojection import Observations, chi2_of, make_observations, residuals


def _problem(seed: int, stereo_share: float) -> tuple[BAState, np.ndarray, np.ndarray, Observations]:
    """Points around 1-5 m in front of 6 cameras (some behind one: negative depth), noisy pixels, a share of them with
    a right coordinate, levels 0-7."""
    rng = np.random.default_rng(seed)
    K, M, E = 6, 400, 1500
    T = np.tile(np.eye(4), (K, 1, 1))
    T[:] = se3_exp_batch(rng.normal(0, 0.1, (K, 6)))
    X = rng.normal(0, 1.0, (M, 3)) + np.array([0, 0, 3.0])
    X[:5, 2] = -2.0  # behind every camera
    obs_pose = rng.integers(0, K, E).astype(np.int64)
    obs_point = rng.integers(0, M, E).astype(np.int64)
    intr = np.tile([517.3, 516.5, 318.6, 255.3], (E, 1)) * rng.uniform(0.99, 1.01, (E, 4))
    uv = rng.uniform(0, 640, (E, 2))
    u_right = np.where(rng.random(E) < stereo_share, uv[:, 0] - rng.uniform(1, 30, E), np.nan)
    bf = np.full(E, 40.0)
    info = 1.0 / 1.2 ** (2 * rng.integers(0, 8, E).astype(float))
    obs = make_observations(uv, u_right, intr, bf, info, 5.991, 7.815)
    return BAState(T, X), obs_pose, obs_point, obs


@pytest.mark.parametrize(("seed", "stereo_share"), [(0, 0.0), (1, 0.3), (2, 1.0)])
def test_compiled_chi2_is_the_numpy_formula_to_the_bit(seed: int, stereo_share: float) -> None:
    state, obs_pose, obs_point, obs = _problem(seed, stereo_share)
    chi2, depth = observation_chi2(state, obs_pose, obs_point, obs)
    p_c = _camera_points(state, obs_pose, obs_point)
    with np.errstate(divide="ignore", invalid="ignore"):
        want = chi2_of(residuals(p_c, obs), obs)
    assert np.array_equal(chi2.view(np.int64), want.view(np.int64))
    assert np.array_equal(depth.view(np.int64), p_c[:, 2].view(np.int64))
    assert (depth < 0).any() and np.isfinite(chi2).all()


def test_a_changed_summation_order_is_caught() -> None:
    """The check above can fail: the camera point summed in plain left-to-right order differs in some last bits."""
    state, obs_pose, obs_point, _ = _problem(3, 0.0)
    R = state.T_c_w[obs_pose, :3, :3]
    X = state.xyz_w[obs_point]
    p = R * X[:, None, :]
    plain = (p[..., 0] + p[..., 1]) + p[..., 2] + state.T_c_w[obs_pose, :3, 3]
    assert not np.array_equal(plain, _camera_points(state, obs_pose, obs_point))
