"""Tracking's compiled motion-only BA (slamkit.pipeline.pose_optimization): same answer as the SciPy backend's
PoseOptimization, recovers the pose, rejects the planted outliers, and refuses what it does not support."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from slamkit_scipy.optimizer import ScipyOptimizer

from slamkit.optim.synthetic import make_pose_problem, pose_errors, with_kannala_brandt
from slamkit.pipeline.pose_optimization import _optimize_pose_kernel, optimize_pose


@pytest.mark.parametrize("seed", range(6))
def test_matches_the_scipy_backend(seed: int) -> None:
    problem, _ = make_pose_problem(np.random.default_rng(seed), n_points=250, outlier_ratio=0.1)
    ours = optimize_pose(problem)
    ref = ScipyOptimizer().optimize_pose(problem)
    np.testing.assert_allclose(ours.T_c_w, ref.T_c_w, atol=1e-9)
    np.testing.assert_array_equal(ours.inliers, ref.inliers)
    assert ours.iterations == ref.iterations
    assert ours.cost_final == pytest.approx(ref.cost_final, rel=1e-9)
    assert ours.cost_initial == pytest.approx(ref.cost_initial, rel=1e-9)


def test_recovers_the_pose_and_rejects_planted_outliers() -> None:
    problem, truth = make_pose_problem(
        np.random.default_rng(11), n_points=300, outlier_ratio=0.15, init_rot_rad=0.05, init_trans_m=0.2
    )
    result = optimize_pose(problem)
    R_err = result.T_c_w[:3, :3] @ truth.T_c_w[:3, :3].T
    angle = np.arccos(np.clip((np.trace(R_err) - 1.0) / 2.0, -1.0, 1.0))
    assert angle < 2e-3
    assert np.linalg.norm(result.T_c_w[:3, 3] - truth.T_c_w[:3, 3]) < 0.02
    assert not np.any(result.inliers & truth.outlier), "a planted outlier was kept"
    assert np.count_nonzero(result.inliers) > 0.9 * np.count_nonzero(~truth.outlier)
    assert result.cost_final < result.cost_initial
    np.testing.assert_allclose(result.T_c_w[:3, :3] @ result.T_c_w[:3, :3].T, np.eye(3), atol=1e-12)


@pytest.mark.parametrize("seed", range(3))
def test_fisheye_matches_the_scipy_backend_and_recovers_the_pose(seed: int) -> None:
    """Kannala-Brandt problems (raw fisheye observations) are solved natively: same answer as the SciPy backend, the
    true pose, the planted outliers flagged; solved as if the pixels were pinhole ones, the pose is far off."""
    pinhole, truth = make_pose_problem(np.random.default_rng(20 + seed), n_points=300, outlier_ratio=0.1)
    problem = with_kannala_brandt(pinhole, truth)
    ours = optimize_pose(problem)
    ref = ScipyOptimizer().optimize_pose(problem)
    np.testing.assert_allclose(ours.T_c_w, ref.T_c_w, atol=1e-9)
    np.testing.assert_array_equal(ours.inliers, ref.inliers)
    rot, pos = pose_errors(ours.T_c_w, truth.T_c_w)
    assert rot < 5e-3 and pos < 0.02
    assert not np.any(ours.inliers & truth.outlier)
    wrong = optimize_pose(replace(problem, camera_model="pinhole", distortion=None))
    assert pose_errors(wrong.T_c_w, truth.T_c_w)[1] > 10 * pos


def test_point_behind_the_camera_is_an_outlier() -> None:
    problem, _ = make_pose_problem(np.random.default_rng(2), n_points=60, outlier_ratio=0.0)
    T = problem.T_c_w_init
    xyz = problem.xyz_w.copy()
    # move point 0 behind the camera, onto the ray that projects to its observation mirrored: same pixel
    p_c = T[:3, :3] @ xyz[0] + T[:3, 3]
    xyz[0] = T[:3, :3].T @ (-p_c - T[:3, 3])
    result = optimize_pose(replace(problem, xyz_w=xyz))
    assert not result.inliers[0]


@pytest.mark.parametrize("seed", range(4))
def test_stereo_matches_the_scipy_backend_and_recovers_the_pose(seed: int) -> None:
    """Stereo/RGB-D observations (u_right = u - bf / z, 3 dof, chi2 7.815): same pose, inliers, iterations and cost
    as the SciPy backend's PoseOptimization; the planted outliers are flagged and the pose recovered."""
    problem, truth = make_pose_problem(
        np.random.default_rng(40 + seed), n_points=250, outlier_ratio=0.1, stereo_ratio=0.6
    )
    ours = optimize_pose(problem)
    ref = ScipyOptimizer().optimize_pose(problem)
    np.testing.assert_allclose(ours.T_c_w, ref.T_c_w, atol=1e-9)
    np.testing.assert_array_equal(ours.inliers, ref.inliers)
    assert ours.iterations == ref.iterations
    assert ours.cost_final == pytest.approx(ref.cost_final, rel=1e-9)
    rot, pos = pose_errors(ours.T_c_w, truth.T_c_w)
    assert rot < 2e-3 and pos < 0.02
    assert not np.any(ours.inliers & truth.outlier)


def test_stereo_right_coordinate_is_used() -> None:
    """A right coordinate shifted by 8 px on every stereo observation (a wrong bf) moves the stereo ones out of the
    7.815 gate: the residual is really 3-dof."""
    problem, _ = make_pose_problem(np.random.default_rng(5), n_points=200, outlier_ratio=0.0, stereo_ratio=1.0)
    good = optimize_pose(problem)
    assert good.inliers.mean() > 0.9
    shifted = optimize_pose(replace(problem, u_right_px=problem.u_right_px + 8.0))
    assert shifted.inliers.mean() < 0.5


def test_rejects_stereo_and_malformed_problems() -> None:
    problem, _ = make_pose_problem(np.random.default_rng(3), n_points=40, stereo_ratio=0.5)
    with pytest.raises(ValueError, match="stereo"):
        optimize_pose(replace(problem, bf=0.0))
    mono, _ = make_pose_problem(np.random.default_rng(3), n_points=40)
    with pytest.raises(ValueError, match=r"uv_px \(N, 2\)"):
        optimize_pose(replace(mono, uv_px=mono.uv_px[:-1]))
    bad = mono.xyz_w.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="finite"):
        optimize_pose(replace(mono, xyz_w=bad))


def test_kernel_releases_the_gil() -> None:
    assert _optimize_pose_kernel.targetoptions.get("nogil") is True
