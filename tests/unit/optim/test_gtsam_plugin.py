"""slamkit_gtsam specifics: convention conversions at the boundary, config validation, the bare reference script."""

from __future__ import annotations

import dataclasses
from typing import Any

import gtsam
import numpy as np
import pytest
from slamkit_gtsam.backend import GtsamOptimizer
from slamkit_gtsam.convert import S_from_similarity3, similarity3_from_S

from slamkit.errors import ConfigError
from slamkit.geometry.sim3 import Sim3
from slamkit.geometry.so3 import so3_exp
from slamkit.optim.costs import essential_graph_residuals
from slamkit.optim.synthetic import make_bundle_problem, make_essential_graph_problem


def test_similarity3_round_trip_and_action() -> None:
    S = Sim3(1.7, so3_exp(np.array([0.1, -0.2, 0.3])), np.array([0.5, -1.0, 2.0]))
    g = similarity3_from_S(S.matrix())
    x = np.array([0.3, 0.2, 1.0])
    assert np.allclose(np.asarray(g.transformFrom(x)), S.act(x), atol=1e-12)  # same transform, x -> s R x + t
    assert np.allclose(S_from_similarity3(g), S.matrix(), atol=1e-12)
    # both tangents are [omega, v, lambda]
    assert np.allclose(gtsam.Similarity3.Logmap(g), S.log(), atol=1e-10)


def test_essential_graph_cost_is_orb_slams_edge_error() -> None:
    problem, _ = make_essential_graph_problem(np.random.default_rng(3), n_keyframes=40, n_edges=50)
    result = GtsamOptimizer().optimize_essential_graph(problem)
    r = essential_graph_residuals(problem, problem.S_c_w)
    assert result.cost_initial == pytest.approx(float((r**2).sum()), rel=1e-9)


def _count_eliminations(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Count GaussianFactorGraph.eliminateSequential calls (the Gauss-Newton driver's eliminations)."""
    calls = [0]
    original = gtsam.GaussianFactorGraph.eliminateSequential

    def counting(self: gtsam.GaussianFactorGraph, *args: Any, **kwargs: Any) -> Any:
        calls[0] += 1
        return original(self, *args, **kwargs)

    monkeypatch.setattr(gtsam.GaussianFactorGraph, "eliminateSequential", counting)
    return calls


@pytest.mark.parametrize("outlier_ratio", [0.0, 0.05])
def test_gauss_newton_stage_lands_where_lm_does(monkeypatch: pytest.MonkeyPatch, outlier_ratio: float) -> None:
    """Two fixed keyframes fix the gauge: the Gauss-Newton driver takes LM's steps (LM takes them all at its damping
    floor) and replaces the confirming iteration by a chord step on the previous Cholesky factor. Same outlier
    flags, poses within 1e-5 m, the same cost to 1e-5, as many iterations as LM, one elimination fewer per stage."""
    problem, truth = make_bundle_problem(
        np.random.default_rng(8), n_free=5, n_fixed=2, n_points=400, n_obs=2000, outlier_ratio=outlier_ratio
    )
    lm = GtsamOptimizer(ba_gauss_newton=False).bundle_adjust(problem)
    calls = _count_eliminations(monkeypatch)
    gn = GtsamOptimizer().bundle_adjust(problem)
    assert gn.iterations == lm.iterations
    assert calls[0] < gn.iterations  # LM eliminates once per iteration: a stage ended on a chord step
    assert np.array_equal(gn.outlier, lm.outlier)
    assert np.abs(gn.T_c_w[:, :3, 3] - lm.T_c_w[:, :3, 3]).max() < 1e-5
    assert gn.cost_final == pytest.approx(lm.cost_final, rel=1e-5)
    assert np.abs(gn.T_c_w[:, :3, 3] - truth.T_c_w[:, :3, 3]).max() < 0.025  # closer than the 30 mm start


def _centres(T_c_w: np.ndarray) -> np.ndarray:
    """(K, 3) camera centres in the world frame of (K, 4, 4) T_c_w."""
    return -np.einsum("kji,kj->ki", T_c_w[:, :3, :3], T_c_w[:, :3, 3])


def test_one_fixed_keyframe_holds_the_scale_gauge(monkeypatch: pytest.MonkeyPatch) -> None:
    """A monocular window with one fixed keyframe leaves the scale free (every free centre and point scaled about
    the fixed centre reprojects the same): the range factor holds the farthest free keyframe's distance, the stage
    runs the Gauss-Newton driver, and the solution is LM's scaled about the fixed centre (the same minimum: same
    outliers, same cost, same rotations)."""
    problem, _ = make_bundle_problem(np.random.default_rng(5), n_free=5, n_fixed=1, n_points=400, n_obs=2000)
    free = ~problem.pose_fixed
    c0 = _centres(problem.T_c_w)[problem.pose_fixed][0]
    d_in = np.linalg.norm(_centres(problem.T_c_w)[free] - c0, axis=1)
    far = int(np.argmax(d_in))
    calls = _count_eliminations(monkeypatch)
    held = GtsamOptimizer().bundle_adjust(problem)
    assert calls[0] > 0
    drifting = GtsamOptimizer(ba_fix_scale_gauge=False).bundle_adjust(problem)
    c_held = _centres(held.T_c_w)[free]
    c_lm = _centres(drifting.T_c_w)[free]
    assert np.linalg.norm(c_held[far] - c0) == pytest.approx(d_in[far], rel=1e-6)
    assert np.array_equal(held.outlier, drifting.outlier)
    assert held.cost_final == pytest.approx(drifting.cost_final, rel=1e-4)
    s = np.linalg.norm(c_held[far] - c0) / np.linalg.norm(c_lm[far] - c0)
    assert np.abs(c0 + s * (c_lm - c0) - c_held).max() < 1e-4
    assert np.abs(held.T_c_w[:, :3, :3] - drifting.T_c_w[:, :3, :3]).max() < 1e-4


def test_gauss_newton_only_where_the_normal_equations_are_definite(monkeypatch: pytest.MonkeyPatch) -> None:
    """A monocular window with one fixed keyframe and its scale left free (``ba_fix_scale_gauge`` off), a point with
    one monocular observation its depth: those stages stay with LM (its damping keeps the system definite); with
    the chord test off the driver's iterations are LM's, one elimination each."""
    calls = _count_eliminations(monkeypatch)
    one_fixed, _ = make_bundle_problem(np.random.default_rng(5), n_free=5, n_fixed=1, n_points=400, n_obs=2000)
    GtsamOptimizer(ba_fix_scale_gauge=False).bundle_adjust(one_fixed)
    assert calls[0] == 0
    problem, _ = make_bundle_problem(np.random.default_rng(8), n_free=5, n_fixed=2, n_points=400, n_obs=2000)
    lone = int(problem.obs_point[0])
    keep = (problem.obs_point != lone) | (np.arange(len(problem.obs_point)) == 0)
    single = dataclasses.replace(
        problem,
        obs_pose=problem.obs_pose[keep],
        obs_point=problem.obs_point[keep],
        uv_px=problem.uv_px[keep],
        u_right_px=problem.u_right_px[keep],
        level=problem.level[keep],
        iterations_second=0,  # the outlier pass would take the lone point out: stage 1 only
    )
    GtsamOptimizer().bundle_adjust(single)
    assert calls[0] == 0
    full = GtsamOptimizer(ba_chord_test_below=0.0).bundle_adjust(problem)
    assert calls[0] == full.iterations


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"lambda_initial": 0.0}, r"optimizer\.lambda_initial = 0\.0"),
        ({"relative_error_tol": -1.0}, r"optimizer\.relative_error_tol = -1\.0"),
        ({"ordering": "AMD"}, r"optimizer\.ordering = 'AMD'"),
        ({"ba_ordering": "NATURAL"}, r"optimizer\.ba_ordering = 'NATURAL'"),
        ({"ba_linear_solver": "CHOLMOD"}, r"optimizer\.ba_linear_solver = 'CHOLMOD'"),
        ({"ba_robust_second_stage": "no"}, r"optimizer\.ba_robust_second_stage = 'no'"),
        ({"ba_lambda_lower_bound": -1.0}, r"optimizer\.ba_lambda_lower_bound = -1\.0"),
        ({"ba_drop_undetermined_points": 1}, r"optimizer\.ba_drop_undetermined_points = 1"),
        ({"ba_predict_convergence": "yes"}, r"optimizer\.ba_predict_convergence = 'yes'"),
        ({"ba_gauss_newton": 1}, r"optimizer\.ba_gauss_newton = 1"),
        ({"ba_chord_test_below": -1.0}, r"optimizer\.ba_chord_test_below = -1\.0"),
        ({"ba_fix_scale_gauge": "on"}, r"optimizer\.ba_fix_scale_gauge = 'on'"),
    ],
)
def test_bad_config_is_rejected(kwargs: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        GtsamOptimizer(**kwargs)


def test_backend_matches_the_bare_script() -> None:
    """The bare script runs GTSAM's own stopping rule and keeps every observed point in the second stage: the
    backend with those two speed rules off does the same iterations to the same result."""
    problem, _ = make_bundle_problem(np.random.default_rng(4), n_free=4, n_fixed=3, n_points=300, n_obs=1500)
    opt = GtsamOptimizer(ba_predict_convergence=False, ba_drop_undetermined_points=False, ba_gauss_newton=False)
    ours = opt.bundle_adjust(problem)
    bare = opt.reference_bundle_adjust(problem)
    assert ours.iterations == bare.iterations
    assert ours.cost_final == pytest.approx(bare.cost_final, rel=1e-6)
    assert np.array_equal(ours.outlier, bare.outlier)
    assert np.allclose(ours.T_c_w, bare.T_c_w, atol=1e-6)


def test_ba_speed_settings_leave_the_solution_unchanged() -> None:
    """The Schur ordering, the sequential solver and the damping floor change how fast LM gets there, not where:
    the same poses, points and outlier flags as GTSAM's defaults (COLAMD, multifrontal, no floor)."""
    problem, _ = make_bundle_problem(np.random.default_rng(5), n_free=5, n_fixed=1, n_points=400, n_obs=2000)
    fast = GtsamOptimizer().bundle_adjust(problem)
    plain = GtsamOptimizer(
        ba_ordering="COLAMD", ba_linear_solver="MULTIFRONTAL_CHOLESKY", ba_lambda_lower_bound=0.0
    ).bundle_adjust(problem)
    assert np.allclose(fast.T_c_w, plain.T_c_w, atol=1e-6)
    assert np.allclose(fast.xyz_w, plain.xyz_w, atol=1e-5)
    assert np.array_equal(fast.outlier, plain.outlier)


def test_ba_outliers_match_the_default_backend() -> None:
    """ORB-SLAM2's LocalBundleAdjustment erases every edge the outlier pass set aside (its chi2 stays the stage-1
    one), not only those failing at the end: the GTSAM backend flags the same observations as the default (SciPy)
    backend, up to a few on the gate's edge (before: 11 of 2000 differed, excluded observations came back)."""
    from slamkit.optim.factory import build_optimizer
    from slamkit.plugins import ComponentRegistry

    registry = ComponentRegistry.discover()
    node = registry.get("optimizer", "scipy").config_node()
    node["worker"] = "inline"
    default = build_optimizer(node, registry)
    problem, _ = make_bundle_problem(
        np.random.default_rng(0), n_free=5, n_fixed=2, n_points=400, n_obs=2000, outlier_ratio=0.05
    )
    ours = GtsamOptimizer().bundle_adjust(problem)
    theirs = default.bundle_adjust(problem)
    assert int((ours.outlier != theirs.outlier).sum()) <= 4
    assert np.allclose(ours.T_c_w[:, :3, 3], theirs.T_c_w[:, :3, 3], atol=1e-3)


def test_converged_first_stage_without_outliers_skips_the_second() -> None:
    """Nothing set aside after a converged first stage: the second stage's cost is the first's, so skipping it
    leaves the solution where LM converged (within its tolerance) and saves its iterations; with outliers set
    aside the second stage runs exactly as before."""
    clean, truth = make_bundle_problem(
        np.random.default_rng(6), n_free=4, n_fixed=2, n_points=300, n_obs=1500, outlier_ratio=0.0, noise_px=0.5
    )
    skip = GtsamOptimizer().bundle_adjust(clean)
    full = GtsamOptimizer(ba_skip_converged_second_stage=False).bundle_adjust(clean)
    assert not skip.outlier.any() and skip.iterations < full.iterations
    assert np.allclose(skip.T_c_w[:, :3, 3], full.T_c_w[:, :3, 3], atol=1e-5)
    assert skip.cost_final == pytest.approx(full.cost_final, rel=1e-4)
    # recovered: within 15 mm of the truth (the keyframes start 30 mm per axis off)
    assert np.abs(skip.T_c_w[:, :3, 3] - truth.T_c_w[:, :3, 3]).max() < 0.015
    noisy, _ = make_bundle_problem(np.random.default_rng(7), n_free=4, n_fixed=2, n_points=300, n_obs=1500)
    a = GtsamOptimizer().bundle_adjust(noisy)
    b = GtsamOptimizer(ba_skip_converged_second_stage=False).bundle_adjust(noisy)
    assert a.outlier.any() and a.iterations == b.iterations
    assert np.array_equal(a.T_c_w, b.T_c_w) and np.array_equal(a.outlier, b.outlier)


def test_predicted_convergence_saves_an_iteration_not_the_solution() -> None:
    """Stopping when the extrapolated remaining decrease is below the tolerance skips the confirming LM iteration
    (a linearization and an elimination) and lands where GTSAM's own test stops, within its tolerance."""
    problem, truth = make_bundle_problem(np.random.default_rng(5), n_free=5, n_fixed=1, n_points=400, n_obs=2000)
    fast = GtsamOptimizer(ba_predict_convergence=True).bundle_adjust(problem)
    plain = GtsamOptimizer(ba_predict_convergence=False).bundle_adjust(problem)
    assert fast.iterations < plain.iterations
    assert np.array_equal(fast.outlier, plain.outlier)
    assert np.abs(fast.T_c_w[:, :3, 3] - plain.T_c_w[:, :3, 3]).max() < 1e-5
    assert fast.cost_final == pytest.approx(plain.cost_final, rel=1e-4)
    assert np.abs(fast.T_c_w[:, :3, 3] - truth.T_c_w[:, :3, 3]).max() < 0.05  # recovered (started 30 mm off)


def test_undetermined_points_leave_the_second_stage() -> None:
    """After the outlier pass some points keep one monocular observation: their depth is free, they add nothing
    to the poses. Leaving them out of the second stage (GTSAM's Cholesky fails on them at the damping floor and LM
    pays rejected tries) and then placing them on their observation's ray gives the poses, outlier flags and
    points of the stage with them in it, within a millimetre."""
    problem, _ = make_bundle_problem(
        np.random.default_rng(0), n_free=5, n_fixed=2, n_points=400, n_obs=2000, outlier_ratio=0.05
    )
    drop = GtsamOptimizer().bundle_adjust(problem)
    keep = GtsamOptimizer(ba_drop_undetermined_points=False).bundle_adjust(problem)
    inliers_per_point = np.bincount(problem.obs_point[~drop.outlier], minlength=len(problem.xyz_w))
    single = inliers_per_point == 1
    assert single.sum() >= 5  # the case is there
    assert np.array_equal(drop.outlier, keep.outlier)
    assert np.abs(drop.T_c_w[:, :3, 3] - keep.T_c_w[:, :3, 3]).max() < 1e-5
    assert np.abs(drop.xyz_w - keep.xyz_w).max() < 1e-3
    # left at their first-stage estimate instead, the single-observation points would be centimetres off
    from slamkit.optim.costs import bundle_chi2

    chi2 = bundle_chi2(problem, drop.T_c_w, drop.xyz_w)
    only = ~drop.outlier & single[problem.obs_point]
    assert chi2[only].max() < 1e-12  # on the ray: reprojection error zero
