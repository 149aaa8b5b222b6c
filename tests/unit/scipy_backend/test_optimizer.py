"""The ``optimizer=scipy`` component: registration, config checks, and problem validation before solving."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from slamkit_scipy.optimizer import ScipyOptimizer

from slamkit.errors import ConfigError, ProblemError
from slamkit.interfaces import Optimizer
from slamkit.optim import synthetic as syn
from slamkit.optim.factory import build_optimizer
from slamkit.plugins import ComponentRegistry


def test_registered_and_built_from_its_config_node() -> None:
    registry = ComponentRegistry.discover()
    node = registry.get("optimizer", "scipy").config_node()
    assert node["worker"] == "inline"
    optimizer = build_optimizer(node, registry)
    assert isinstance(optimizer, ScipyOptimizer)
    assert isinstance(optimizer, Optimizer)
    assert optimizer.name == "scipy"
    assert optimizer.eg_settings.lambda_init == 1e-16


@pytest.mark.parametrize(
    ("key", "value"),
    [("lm_tau", -1.0), ("lm_max_trials", 0), ("lm_rel_tol", float("nan")), ("ba_robust_second_stage", "no")],
)
def test_bad_config_names_the_key(key: str, value: object) -> None:
    with pytest.raises(ConfigError, match=f"optimizer.{key}"):
        ScipyOptimizer(**{key: value})  # type: ignore[arg-type]


def test_nan_pose_problem_rejected_before_solving() -> None:
    problem, _ = syn.make_pose_problem(np.random.default_rng(0), n_points=50)
    xyz = problem.xyz_w.copy()
    xyz[7, 1] = np.nan
    with pytest.raises(ProblemError, match=r"xyz_w.*index \(7, 1\)"):
        ScipyOptimizer().optimize_pose(replace(problem, xyz_w=xyz))


def test_bundle_without_fixed_variable_rejected() -> None:
    problem, _ = syn.make_bundle_problem(np.random.default_rng(1), n_free=2, n_fixed=1, n_points=60, n_obs=150)
    free = replace(problem, pose_fixed=np.zeros_like(problem.pose_fixed))
    with pytest.raises(ProblemError, match="no fixed variable"):
        ScipyOptimizer().bundle_adjust(free)


def test_graph_without_fixed_keyframe_rejected() -> None:
    problem, _ = syn.make_essential_graph_problem(np.random.default_rng(2), n_keyframes=20, n_edges=25)
    with pytest.raises(ProblemError, match="no fixed keyframe"):
        ScipyOptimizer().optimize_essential_graph(replace(problem, fixed=np.zeros_like(problem.fixed)))


def test_sim3_with_too_few_matches_rejected() -> None:
    problem, _ = syn.make_sim3_problem(np.random.default_rng(3), n_matches=20)
    short = replace(
        problem,
        xyz1_c1=problem.xyz1_c1[:2],
        xyz2_c2=problem.xyz2_c2[:2],
        uv1_px=problem.uv1_px[:2],
        uv2_px=problem.uv2_px[:2],
        level1=problem.level1[:2],
        level2=problem.level2[:2],
    )
    with pytest.raises(ProblemError, match="at least 3"):
        ScipyOptimizer().optimize_sim3(short)


def test_runs_in_a_worker_process() -> None:
    """optimizer.worker=process: the same results through slamkit.optim.worker (problems/results pickled)."""
    registry = ComponentRegistry.discover()
    node = {**registry.get("optimizer", "scipy").config_node(), "worker": "process"}
    problem, _ = syn.make_pose_problem(np.random.default_rng(4), n_points=80)
    remote = build_optimizer(node, registry)
    try:
        result = remote.optimize_pose(problem)
    finally:
        remote.close()  # type: ignore[attr-defined]
    local = ScipyOptimizer().optimize_pose(problem)
    np.testing.assert_array_equal(result.T_c_w, local.T_c_w)
    np.testing.assert_array_equal(result.inliers, local.inliers)
