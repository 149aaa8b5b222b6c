"""Synthetic problems: seeded, consistent with their truth, with the promised noise, outliers and drift."""

from __future__ import annotations

import numpy as np
import pytest

from slamkit.optim.costs import bundle_chi2, essential_graph_cost, huber_cost, pose_chi2, sim3_chi2
from slamkit.optim.synthetic import (
    INTRINSICS,
    look_at,
    make_bundle_problem,
    make_essential_graph_problem,
    make_pose_problem,
    make_sim3_problem,
    pose_errors,
    sim3_errors,
)


def test_same_seed_same_problem() -> None:
    a, ta = make_bundle_problem(np.random.default_rng(5), n_free=3, n_fixed=2, n_points=100, n_obs=400)
    b, tb = make_bundle_problem(np.random.default_rng(5), n_free=3, n_fixed=2, n_points=100, n_obs=400)
    assert np.array_equal(a.uv_px, b.uv_px) and np.array_equal(a.T_c_w, b.T_c_w)
    assert np.array_equal(ta.outlier, tb.outlier)
    c, _ = make_bundle_problem(np.random.default_rng(6), n_free=3, n_fixed=2, n_points=100, n_obs=400)
    assert not np.array_equal(a.uv_px, c.uv_px)


def test_look_at_points_the_optical_axis_at_the_target() -> None:
    T = look_at(np.array([1.0, 2.0, 1.5]), np.array([6.0, 2.0, 1.5]))
    target_c = T[:3, :3] @ np.array([6.0, 2.0, 1.5]) + T[:3, 3]
    assert np.allclose(target_c, [0.0, 0.0, 5.0])
    # world z up is image up (camera y down)
    up_c = T[:3, :3] @ np.array([0.0, 0.0, 1.0])
    assert up_c[1] == pytest.approx(-1.0)


def test_pose_problem_noise_and_outliers_match_the_model() -> None:
    problem, truth = make_pose_problem(np.random.default_rng(7), n_points=2000, stereo_ratio=0.0, outlier_ratio=0.03)
    chi2 = pose_chi2(problem, truth.T_c_w)
    assert truth.outlier.sum() == 60
    # Clean mono observations: chi2 with 2 dof (mean 2; 95 % under 5.991).
    assert chi2[~truth.outlier].mean() == pytest.approx(2.0, rel=0.1)
    assert (chi2[~truth.outlier] > 5.991).mean() == pytest.approx(0.05, abs=0.015)
    assert chi2[truth.outlier].min() > 10.0**2  # 15..40 sigma displacements, plus noise
    z = problem.xyz_w @ truth.T_c_w[2, :3] + truth.T_c_w[2, 3]
    assert z.min() >= 2.0 and z.max() <= 8.0
    assert problem.level.min() == 0 and problem.level.max() == 7


def test_stereo_observations_have_the_right_disparity() -> None:
    problem, truth = make_pose_problem(np.random.default_rng(8), n_points=500, stereo_ratio=0.5, noise_px=0.0)
    stereo = np.isfinite(problem.u_right_px) & ~truth.outlier
    assert 0.4 < stereo.mean() < 0.6
    assert np.allclose(pose_chi2(problem, truth.T_c_w)[~truth.outlier], 0.0, atol=1e-12)


def test_bundle_problem_structure() -> None:
    problem, truth = make_bundle_problem(np.random.default_rng(9))
    assert problem.T_c_w.shape == (20, 4, 4) and len(problem.xyz_w) == 2000 and len(problem.obs_pose) == 20000
    assert np.array_equal(problem.T_c_w[problem.pose_fixed], truth.T_c_w[problem.pose_fixed])
    assert problem.pose_fixed.sum() == 10
    assert truth.outlier.sum() == 400  # 2 %
    seen = np.bincount(problem.obs_point, minlength=2000)
    clean = np.bincount(problem.obs_point[~truth.outlier], minlength=2000)
    assert seen.min() >= 2 and clean.min() >= 2
    chi2 = bundle_chi2(problem, truth.T_c_w, truth.xyz_w)
    assert chi2[~truth.outlier].mean() == pytest.approx(2.0, rel=0.1)
    assert chi2[truth.outlier].min() > 10.0**2  # 15..40 sigma displacements, plus noise
    # no duplicate (keyframe, point) pairs
    pairs = problem.obs_pose * 10000 + problem.obs_point
    assert len(np.unique(pairs)) == len(pairs)


def test_sim3_problem_truth_explains_the_clean_matches() -> None:
    problem, truth = make_sim3_problem(np.random.default_rng(10), n_matches=300, scale=1.4, noise_px=0.0)
    e1, e2 = sim3_chi2(problem, truth.S_12)
    assert np.allclose(e1[~truth.outlier], 0.0, atol=1e-12) and np.allclose(e2[~truth.outlier], 0.0, atol=1e-12)
    assert (e1[truth.outlier] > 100).all() and (e2[truth.outlier] > 10).all()
    s = np.cbrt(np.linalg.det(truth.S_12[:3, :3]))
    assert s == pytest.approx(1 / 1.4)
    fixed, ftruth = make_sim3_problem(np.random.default_rng(10), fix_scale=True)
    assert np.cbrt(np.linalg.det(fixed.S_12_init[:3, :3])) == pytest.approx(1.0, abs=1e-12)
    assert np.cbrt(np.linalg.det(ftruth.S_12[:3, :3])) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("use_sim3", [True, False])
def test_essential_graph_truth_and_drift(use_sim3: bool) -> None:
    problem, truth = make_essential_graph_problem(
        np.random.default_rng(11), use_sim3=use_sim3, noise_rot_rad=0.0, noise_trans_m=0.0, noise_log_scale=0.0
    )
    assert len(problem.S_c_w) == 1600 and len(problem.edge_i) == 2000
    assert problem.fixed.sum() == 1 and problem.fixed[0]
    assert essential_graph_cost(problem, truth.S_c_w) == pytest.approx(0.0, abs=1e-18)
    _rot, pos, scale = sim3_errors(problem.S_c_w, truth.S_c_w)
    assert pos[-1] > 1.0  # accumulated drift at the loop
    assert pos[0] == 0.0
    if use_sim3:
        assert scale[-1] > 0.05
    else:
        assert scale.max() < 1e-12
    (loop,) = truth.loop_edges
    assert (problem.edge_i[loop], problem.edge_j[loop]) == (1599, 0)
    # the loop closes: consecutive keyframes ~1 m apart and the last near the first
    centres = np.linalg.inv(truth.S_c_w)[:, :3, 3]
    assert np.linalg.norm(centres[-1] - centres[0]) < 2.0


def test_error_measures() -> None:
    T = look_at(np.zeros(3), np.array([1.0, 0.0, 0.0]))
    T2 = T.copy()
    T2[:3, 3] += T[:3, :3] @ np.array([0.0, 0.0, -0.5])  # camera moved 0.5 m along its viewing ray
    rot, pos = pose_errors(T2, T)
    assert rot == pytest.approx(0.0, abs=1e-7) and pos == pytest.approx(0.5)
    S = T.copy()
    S[:3, :] *= 2.0
    S[3] = [0, 0, 0, 1]
    _r, p, s = sim3_errors(S, T)
    assert s == pytest.approx(np.log(2.0)) and p == pytest.approx(0.0, abs=1e-12)
    assert huber_cost(np.array([1.0, 9.0]), 4.0).tolist() == [1.0, 2 * 2 * 3 - 4.0]
    assert INTRINSICS.tolist() == [520.0, 520.0, 320.0, 240.0]
