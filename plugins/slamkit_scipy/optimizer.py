"""The SciPy optimizer backend: every ORB-SLAM optimization with our own LM in numpy/scipy.sparse.

Each method validates its problem (slamkit.optim.validation, ProblemError before any solving), then runs
the solver module for that problem. Reported costs use slamkit.optim.costs (g2o's Huber on chi2, identical
for every backend); the pose-graph cost is the same formula evaluated vectorised here.
"""

from __future__ import annotations

import math

from slamkit.errors import ConfigError
from slamkit.interfaces import AbortToken
from slamkit.optim.costs import bundle_cost, pose_cost, sim3_cost
from slamkit.optim.validation import (
    validate_bundle_problem,
    validate_essential_graph_problem,
    validate_pose_problem,
    validate_sim3_problem,
)
from slamkit.problems import (
    BundleProblem,
    BundleResult,
    EssentialGraphProblem,
    EssentialGraphResult,
    PoseOnlyProblem,
    PoseOnlyResult,
    Sim3Problem,
    Sim3Result,
)
from slamkit_scipy.bundle import bundle_adjust
from slamkit_scipy.lm import LMSettings
from slamkit_scipy.pose_graph import optimize_essential_graph
from slamkit_scipy.pose_only import optimize_pose
from slamkit_scipy.sim3_align import optimize_sim3


def _positive_float(value: object, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value <= 0:
        raise ConfigError(f"optimizer.{key}: expected a finite number > 0, got {value!r}")
    return float(value)


def _positive_int(value: object, key: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ConfigError(f"optimizer.{key}: expected an integer > 0, got {value!r}")
    return int(value)


def _flag(value: object, key: str) -> bool:
    if not isinstance(value, bool):
        raise ConfigError(f"optimizer.{key}: expected true or false, got {value!r}")
    return value


class ScipyOptimizer:
    """slamkit.interfaces.Optimizer on numpy/scipy: LM with IRLS Huber, Schur-complement BA, sparse pose graph.

    lm_tau: initial damping as a fraction of max diag(H); lm_max_trials: damped solves per iteration;
    lm_rel_tol: stop early when an accepted step lowers the cost by less than this fraction;
    ba_robust_second_stage: keep the Huber kernel after BA's outlier pass (ORB-SLAM drops it);
    ba_dense_max: largest reduced camera system (6 x free keyframes) solved densely, beyond it sparse LU;
    pose_behind_is_outlier: motion-only BA classifies points behind the camera as outliers;
    eg_lambda_init: absolute initial damping of the essential-graph LM (ORB-SLAM: 1e-16, i.e. Gauss-Newton
    first; a damping relative to diag(H) crawls when the loop error sits on one edge).
    """

    name = "scipy"

    def __init__(
        self,
        lm_tau: float = 1e-5,
        lm_max_trials: int = 10,
        lm_rel_tol: float = 1e-10,
        ba_robust_second_stage: bool = False,
        ba_dense_max: int = 3000,
        pose_behind_is_outlier: bool = True,
        eg_lambda_init: float = 1e-16,
    ) -> None:
        self.settings = LMSettings(
            tau=_positive_float(lm_tau, "lm_tau"),
            max_trials=_positive_int(lm_max_trials, "lm_max_trials"),
            rel_tol=_positive_float(lm_rel_tol, "lm_rel_tol"),
        )
        self.ba_robust_second_stage = _flag(ba_robust_second_stage, "ba_robust_second_stage")
        self.ba_dense_max = _positive_int(ba_dense_max, "ba_dense_max")
        self.pose_behind_is_outlier = _flag(pose_behind_is_outlier, "pose_behind_is_outlier")
        self.eg_settings = LMSettings(
            tau=self.settings.tau,
            lambda_init=_positive_float(eg_lambda_init, "eg_lambda_init"),
            max_trials=self.settings.max_trials,
            rel_tol=self.settings.rel_tol,
        )

    def optimize_pose(self, problem: PoseOnlyProblem) -> PoseOnlyResult:
        """Motion-only BA with ORB-SLAM's rounds of chi-square re-classification (slamkit_scipy.pose_only)."""
        validate_pose_problem(problem, supports_rig=True, backend=self.name)
        result = optimize_pose(problem, self.settings, self.pose_behind_is_outlier)
        result.cost_initial = pose_cost(problem, problem.T_c_w_init)
        result.cost_final = pose_cost(problem, result.T_c_w, result.inliers)
        return result

    def bundle_adjust(self, problem: BundleProblem, abort: AbortToken | None = None) -> BundleResult:
        """Local/global BA (slamkit_scipy.bundle); ``abort`` is checked before every LM iteration."""
        validate_bundle_problem(problem, supports_rig=True, backend=self.name)
        result = bundle_adjust(
            problem, self.settings, abort, self.ba_robust_second_stage, self.ba_dense_max, report_costs=False
        )
        result.cost_initial = bundle_cost(problem, problem.T_c_w, problem.xyz_w)
        result.cost_final = bundle_cost(problem, result.T_c_w, result.xyz_w, ~result.outlier)
        return result

    def optimize_sim3(self, problem: Sim3Problem) -> Sim3Result:
        """Relative Sim3 with the bidirectional reprojection error (slamkit_scipy.sim3_align)."""
        validate_sim3_problem(problem)
        result = optimize_sim3(problem, self.settings)
        result.cost_initial = sim3_cost(problem, problem.S_12_init)
        result.cost_final = sim3_cost(problem, result.S_12, result.inliers)
        return result

    def optimize_essential_graph(self, problem: EssentialGraphProblem) -> EssentialGraphResult:
        """Essential-graph optimization in Sim3 (or SE3 when use_sim3 is False) (slamkit_scipy.pose_graph)."""
        validate_essential_graph_problem(problem)
        return optimize_essential_graph(problem, self.eg_settings)
