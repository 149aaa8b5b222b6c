"""The SciPy backend recovers known truth on the project's seeded synthetic problems.

Problems come from slamkit.optim.synthetic (noise 1 px scaled by the pyramid level, planted outliers).
Tolerances are a few times the noise-limited accuracy of each problem size.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from slamkit_scipy.bundle import bundle_adjust
from slamkit_scipy.optimizer import ScipyOptimizer

from slamkit.optim import synthetic as syn
from slamkit.optim.costs import bundle_chi2, bundle_cost, essential_graph_cost, pose_chi2


class CountdownToken:
    """An abort token that becomes set after ``n`` polls (is_set calls)."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.polls = 0

    def is_set(self) -> bool:
        self.polls += 1
        return self.polls > self.n


@pytest.fixture(scope="module")
def opt() -> ScipyOptimizer:
    return ScipyOptimizer()


@pytest.mark.parametrize("stereo_ratio", [0.0, 0.5])
def test_pose_recovered_and_outliers_flagged(opt: ScipyOptimizer, stereo_ratio: float) -> None:
    problem, truth = syn.make_pose_problem(np.random.default_rng(10), stereo_ratio=stereo_ratio)
    result = opt.optimize_pose(problem)
    rot, pos = syn.pose_errors(result.T_c_w, truth.T_c_w)
    assert rot < 3e-3 and pos < 1e-2
    assert not result.inliers[truth.outlier].any()  # every planted outlier rejected
    assert result.inliers[~truth.outlier].mean() > 0.9
    # The final classification is the chi-square gate at the final pose (ORB-SLAM re-classifies every round).
    chi2 = pose_chi2(problem, result.T_c_w)
    gate = np.where(np.isfinite(problem.u_right_px), problem.chi2_stereo, problem.chi2_mono)
    np.testing.assert_array_equal(result.inliers, chi2 <= gate)
    assert result.cost_final < 0.1 * result.cost_initial
    assert result.iterations <= problem.rounds * problem.iterations_per_round


def test_pose_outliers_of_an_early_round_come_back(opt: ScipyOptimizer) -> None:
    """From a poor initial pose the first round's gate rejects good matches; later rounds re-admit them."""
    problem, truth = syn.make_pose_problem(
        np.random.default_rng(11), outlier_ratio=0.0, init_rot_rad=0.03, init_trans_m=0.3
    )
    first = opt.optimize_pose(replace(problem, rounds=1, iterations_per_round=1))
    full = opt.optimize_pose(problem)
    assert (~first.inliers).sum() > 10  # one round from far away misclassifies many
    assert full.inliers.mean() > 0.93  # ... which come back (only the ~5% chi-square tail stays out)
    rot, pos = syn.pose_errors(full.T_c_w, truth.T_c_w)
    assert rot < 3e-3 and pos < 1e-2


def test_pose_points_behind_the_camera_are_outliers(opt: ScipyOptimizer) -> None:
    problem, truth = syn.make_pose_problem(np.random.default_rng(12), n_points=200, outlier_ratio=0.0)
    xyz = problem.xyz_w.copy()
    T = truth.T_c_w
    centre = -T[:3, :3].T @ T[:3, 3]
    xyz[:5] = centre - (xyz[:5] - centre)  # mirrored through the camera centre: behind it, same pixel ray
    result = opt.optimize_pose(replace(problem, xyz_w=xyz))
    assert not result.inliers[:5].any()
    rot, pos = syn.pose_errors(result.T_c_w, truth.T_c_w)
    assert rot < 3e-3 and pos < 1e-2


def _small_ba(seed: int, stereo_ratio: float = 0.0):  # type: ignore[no-untyped-def]
    return syn.make_bundle_problem(
        np.random.default_rng(seed), n_free=4, n_fixed=3, n_points=300, n_obs=1600, stereo_ratio=stereo_ratio
    )


@pytest.mark.parametrize("stereo_ratio", [0.0, 0.4])
def test_bundle_recovers_truth_and_keeps_fixed(opt: ScipyOptimizer, stereo_ratio: float) -> None:
    problem, truth = _small_ba(20, stereo_ratio)
    result = opt.bundle_adjust(problem)
    free = ~problem.pose_fixed
    rot, pos = syn.pose_errors(result.T_c_w[free], truth.T_c_w[free])
    rot0, pos0 = syn.pose_errors(problem.T_c_w[free], truth.T_c_w[free])
    # Noise-limited optimum of this small problem (the noise-free test below recovers the truth exactly).
    assert rot.max() < 4e-3 and pos.max() < 2.5e-2
    assert pos.max() < 0.4 * pos0.max() and rot.max() < 0.4 * rot0.max()
    np.testing.assert_array_equal(result.T_c_w[problem.pose_fixed], problem.T_c_w[problem.pose_fixed])
    assert result.outlier[truth.outlier].all()
    assert result.outlier[~truth.outlier].mean() < 0.08  # chi-square 95% gate: ~5% of inliers
    # Outliers at the end fail the gate (or were excluded by the mid-way pass, as in ORB-SLAM).
    chi2 = bundle_chi2(problem, result.T_c_w, result.xyz_w)
    gate = np.where(np.isfinite(problem.u_right_px), problem.chi2_stereo, problem.chi2_mono)
    assert np.all(chi2[~result.outlier] <= gate[~result.outlier])
    assert result.cost_final < 0.2 * result.cost_initial
    assert not result.aborted
    point_err = np.linalg.norm(result.xyz_w - truth.xyz_w, axis=1)
    assert np.median(point_err) < 0.5 * np.median(np.linalg.norm(problem.xyz_w - truth.xyz_w, axis=1))


def test_bundle_noise_free_recovers_truth_exactly(opt: ScipyOptimizer) -> None:
    problem, truth = syn.make_bundle_problem(
        np.random.default_rng(25), n_free=4, n_fixed=3, n_points=300, n_obs=1600, noise_px=0.0, outlier_ratio=0.0
    )
    result = opt.bundle_adjust(replace(problem, iterations_first=20, iterations_second=20))
    rot, pos = syn.pose_errors(result.T_c_w, truth.T_c_w)
    assert rot.max() < 1e-7 and pos.max() < 1e-7
    np.testing.assert_allclose(result.xyz_w, truth.xyz_w, atol=1e-7)
    assert not result.outlier.any()
    assert result.cost_final < 1e-12


def test_bundle_fixed_points_stay(opt: ScipyOptimizer) -> None:
    problem, _ = _small_ba(21)
    point_fixed = np.zeros(len(problem.xyz_w), dtype=bool)
    point_fixed[::3] = True
    result = opt.bundle_adjust(replace(problem, point_fixed=point_fixed))
    np.testing.assert_array_equal(result.xyz_w[point_fixed], problem.xyz_w[point_fixed])
    assert not np.array_equal(result.xyz_w[~point_fixed], problem.xyz_w[~point_fixed])


def test_bundle_dense_and_sparse_reduced_system_agree() -> None:
    problem, _ = _small_ba(22)
    dense = ScipyOptimizer(ba_dense_max=3000).bundle_adjust(problem)
    sparse = ScipyOptimizer(ba_dense_max=1).bundle_adjust(problem)
    np.testing.assert_allclose(dense.T_c_w, sparse.T_c_w, atol=1e-8)
    np.testing.assert_array_equal(dense.outlier, sparse.outlier)


def test_bundle_costs_reported_once_by_the_optimizer(opt: ScipyOptimizer) -> None:
    """The optimizer asks the solver for no cost report (it computes slamkit.optim.costs' own): the same solution as
    with the solver's report, and the reported costs are bundle_cost's at the input and at the inliers of the result."""
    problem, _ = _small_ba(23)
    reported = bundle_adjust(problem, opt.settings)
    bare = bundle_adjust(problem, opt.settings, report_costs=False)
    assert np.isnan(bare.cost_initial) and np.isnan(bare.cost_final)
    np.testing.assert_array_equal(bare.T_c_w, reported.T_c_w)
    np.testing.assert_array_equal(bare.xyz_w, reported.xyz_w)
    np.testing.assert_array_equal(bare.outlier, reported.outlier)
    result = opt.bundle_adjust(problem)
    np.testing.assert_array_equal(result.T_c_w, reported.T_c_w)
    assert result.cost_initial == bundle_cost(problem, problem.T_c_w, problem.xyz_w)
    assert result.cost_final == bundle_cost(problem, result.T_c_w, result.xyz_w, ~result.outlier)
    np.testing.assert_allclose([result.cost_initial, result.cost_final], [reported.cost_initial, reported.cost_final])


def test_bundle_abort_before_start_returns_the_input(opt: ScipyOptimizer) -> None:
    problem, _ = _small_ba(23)
    result = opt.bundle_adjust(problem, abort=CountdownToken(0))
    assert result.aborted and result.iterations == 0
    np.testing.assert_array_equal(result.T_c_w, problem.T_c_w)
    assert result.cost_final <= result.cost_initial


def test_bundle_abort_midway_returns_a_partial_improvement(opt: ScipyOptimizer) -> None:
    problem, _ = _small_ba(24)
    token = CountdownToken(2)
    result = opt.bundle_adjust(problem, abort=token)
    full = opt.bundle_adjust(problem)
    assert result.aborted and result.iterations == 2
    assert full.iterations > result.iterations
    assert np.all(np.isfinite(result.T_c_w)) and np.all(np.isfinite(result.xyz_w))
    assert result.cost_final < 0.5 * result.cost_initial


@pytest.mark.parametrize("fix_scale", [False, True])
def test_sim3_recovered(opt: ScipyOptimizer, fix_scale: bool) -> None:
    problem, truth = syn.make_sim3_problem(
        np.random.default_rng(30), fix_scale=fix_scale, scale=1.0 if fix_scale else 1.4
    )
    result = opt.optimize_sim3(problem)
    rot, pos, log_s = syn.sim3_errors(result.S_12, truth.S_12)
    assert rot < 3e-3 and pos < 2e-2 and log_s < 1e-2
    assert not result.inliers[truth.outlier].any()
    assert result.inliers[~truth.outlier].mean() > 0.9
    if fix_scale:
        assert np.linalg.det(result.S_12[:3, :3]) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("use_sim3", [True, False])
def test_essential_graph_recovered(opt: ScipyOptimizer, use_sim3: bool) -> None:
    problem, truth = syn.make_essential_graph_problem(
        np.random.default_rng(40), n_keyframes=300, n_edges=400, use_sim3=use_sim3
    )
    result = opt.optimize_essential_graph(problem)
    rot0, pos0, ls0 = syn.sim3_errors(problem.S_c_w, truth.S_c_w)
    rot, pos, ls = syn.sim3_errors(result.S_c_w, truth.S_c_w)
    # Noise-limited: 1e-4 rad of rotation noise per edge over a ~300 m loop leaves ~0.1 m.
    assert pos.max() < 0.2 * pos0.max() and rot.max() < 0.5 * rot0.max()
    assert pos.max() < 0.15 and rot.max() < 4e-3
    np.testing.assert_array_equal(result.S_c_w[problem.fixed], problem.S_c_w[problem.fixed])
    if not use_sim3:
        np.testing.assert_allclose(np.linalg.det(result.S_c_w[:, :3, :3]), 1.0, atol=1e-9)
    else:
        assert ls.max() < 0.1 * ls0.max()
    # The reported cost is the shared definition (slamkit.optim.costs), evaluated independently.
    assert result.cost_final == pytest.approx(essential_graph_cost(problem, result.S_c_w), rel=1e-6)
    assert result.cost_initial == pytest.approx(essential_graph_cost(problem, problem.S_c_w), rel=1e-9)


def test_bundle_structure_only_and_motion_only_variants(opt: ScipyOptimizer) -> None:
    """All poses fixed (points only: no reduced system) and all points fixed (poses only: no points to eliminate)."""
    problem, truth = _small_ba(26)
    points_only = replace(problem, pose_fixed=np.ones_like(problem.pose_fixed), T_c_w=truth.T_c_w.copy())
    result = opt.bundle_adjust(points_only)
    err = np.linalg.norm(result.xyz_w - truth.xyz_w, axis=1)
    assert np.median(err) < 0.3 * np.median(np.linalg.norm(problem.xyz_w - truth.xyz_w, axis=1))
    np.testing.assert_array_equal(result.T_c_w, truth.T_c_w)
    poses_only = replace(problem, point_fixed=np.ones_like(problem.point_fixed), xyz_w=truth.xyz_w.copy())
    result = opt.bundle_adjust(poses_only)
    free = ~problem.pose_fixed
    rot, pos = syn.pose_errors(result.T_c_w[free], truth.T_c_w[free])
    assert rot.max() < 2e-3 and pos.max() < 1e-2
    np.testing.assert_array_equal(result.xyz_w, truth.xyz_w)
