"""GtsamOptimizer: the four ORB-SLAM optimizations with GTSAM factors and Levenberg-Marquardt.

- Motion-only BA: GenericProjectionFactorCal3_S2 / GenericStereoFactor3D on one Pose3, points held by tight priors
  (GenericProjectionFactorCal3Fisheye for a Kannala-Brandt problem: GTSAM's Cal3Fisheye is the same equidistant
  model, one factor per observation);
  ORB-SLAM's rounds (4 x 10 iterations, each restarting from the initial pose) with chi-square classification
  between rounds (outliers of one round may come back).
- Bundle adjustment: projection/stereo factors, Huber with sigma = scale_factor^level; iterations_first, then the
  outlier pass (chi2 gate or negative depth, vectorised in numpy), then iterations_second without them and, as
  ORB-SLAM2, without the Huber kernel. The abort token is checked between LM iterations (we drive
  ``optimizer.iterate()`` ourselves: one Python call per iteration of 10-100+ ms). Elimination: points first, then
  poses (the Schur complement g2o forms), sequential Cholesky, damping never below ``ba_lambda_lower_bound``
  (measured on recorded real local BAs: docs/BENCHMARKS.md "Optimizer backends"). LM stops at GTSAM's relative
  decrease test or, with ``ba_predict_convergence`` (off by default: fr1_xyz tracked worse with it), one iteration
  earlier when the extrapolated remaining decrease is already below it; the second stage leaves out points with one monocular observation left
  (``ba_drop_undetermined_points``; docs/BENCHMARKS.md, branch ``gtsam2``). A stage whose undamped normal
  equations are definite (two fixed keyframes, or one with stereo observations; every free point with 3 residual
  rows) runs a Gauss-Newton driver over GTSAM's linearization and sequential Cholesky instead, whose confirming
  iteration is a chord step on the previous factor (``ba_gauss_newton``; docs/BENCHMARKS.md, branch ``gtsamba``).
- Relative Sim3: one vectorised CustomFactor over all matches (slamkit_gtsam.sim3_factor).
- Essential graph: BetweenFactorSimilarity3 (or BetweenFactorPose3 in the SE3 variant) on the inverse poses, whose
  error is exactly log(S_ij S_jw S_iw^-1).

Fixed variables are held by priors of sigma ``fixed_sigma`` and returned exactly as given. Mono observations are
inserted per (keyframe, level) with gtsam.utilities.insertProjectionFactors (a C++ loop), so the only Python loop
over observations is over stereo ones. Keys are small integers (points 0..M-1, poses M..M+K-1) because that
utility takes keys as doubles.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import gtsam
import numpy as np
from numpy.typing import NDArray

from slamkit.errors import ConfigError
from slamkit.interfaces import AbortToken
from slamkit.optim.costs import bundle_chi2, bundle_cost, huber_cost, pose_chi2, pose_cost, sim3_chi2, sim3_cost
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
from slamkit_gtsam.convert import (
    S_from_similarity3,
    invert_rigid,
    pose3_from_T,
    poses_from_extract,
    similarity3_from_S,
)
from slamkit_gtsam.sim3_factor import Sim3MatchesResidual, make_sim3_factor

F64 = NDArray[np.float64]
B = NDArray[np.bool_]
I64 = NDArray[np.int64]

_ORDERINGS = ("COLAMD", "METIS")
_BA_ORDERINGS = ("SCHUR", "COLAMD", "METIS")
_LINEAR_SOLVERS = ("MULTIFRONTAL_CHOLESKY", "SEQUENTIAL_CHOLESKY", "MULTIFRONTAL_QR", "SEQUENTIAL_QR")
_MIN_POSE_EDGES = 10  # ORB-SLAM PoseOptimization stops its rounds when fewer edges remain


@dataclass
class _LmRun:
    """values: the final estimate; iterations done; aborted by the token; converged: stopped by the
    convergence test (decrease below tolerance, or no decrease), not by the iteration count or the token."""

    values: gtsam.Values
    iterations: int
    aborted: bool
    converged: bool = False


class GtsamOptimizer:
    """slamkit's Optimizer on GTSAM. Config: Levenberg-Marquardt settings (see slamkit_gtsam.plugin)."""

    name = "gtsam"
    #: GTSAM's Python wrapper holds the GIL through optimize/linearize: the threaded runner runs local mapping's
    #: and loop closing's optimizations in a worker process (slamkit.app._background_optimizer).
    holds_gil = True

    @staticmethod
    def reference_bundle_adjust(problem: BundleProblem) -> BundleResult:
        """The same BA as a bare GTSAM script (no slamkit machinery): the benchmark's ``gtsam_bare`` row."""
        return reference_bundle_adjust(problem)

    def __init__(
        self,
        lambda_initial: float = 1e-5,
        lambda_factor: float = 10.0,
        lambda_upper_bound: float = 1e5,
        relative_error_tol: float = 1e-5,
        absolute_error_tol: float = 0.0,
        fixed_sigma: float = 1e-8,
        ordering: str = "COLAMD",
        linear_solver: str = "MULTIFRONTAL_CHOLESKY",
        ba_ordering: str = "SCHUR",
        ba_linear_solver: str = "SEQUENTIAL_CHOLESKY",
        ba_robust_second_stage: bool = False,
        use_fixed_lambda_factor: bool = True,
        ba_lambda_lower_bound: float = 1e-5,
        ba_skip_converged_second_stage: bool = True,
        ba_drop_undetermined_points: bool = True,
        ba_predict_convergence: bool = False,
        ba_gauss_newton: bool = True,
        ba_chord_test_below: float = 1e-3,
        ba_fix_scale_gauge: bool = True,
    ) -> None:
        for key, value in (
            ("lambda_initial", lambda_initial),
            ("lambda_factor", lambda_factor),
            ("lambda_upper_bound", lambda_upper_bound),
            ("fixed_sigma", fixed_sigma),
        ):
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ConfigError(f"optimizer.{key} = {value!r}: expected a finite number > 0")
        for key, value in (
            ("relative_error_tol", relative_error_tol),
            ("absolute_error_tol", absolute_error_tol),
            ("ba_lambda_lower_bound", ba_lambda_lower_bound),
            ("ba_chord_test_below", ba_chord_test_below),
        ):
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ConfigError(f"optimizer.{key} = {value!r}: expected a finite number >= 0")
        for key, choice, allowed in (
            ("ordering", ordering, _ORDERINGS),
            ("ba_ordering", ba_ordering, _BA_ORDERINGS),
            ("linear_solver", linear_solver, _LINEAR_SOLVERS),
            ("ba_linear_solver", ba_linear_solver, _LINEAR_SOLVERS),
        ):
            if choice not in allowed:
                raise ConfigError(f"optimizer.{key} = {choice!r}: expected one of {', '.join(allowed)}")
        for key, flag in (
            ("ba_robust_second_stage", ba_robust_second_stage),
            ("use_fixed_lambda_factor", use_fixed_lambda_factor),
            ("ba_skip_converged_second_stage", ba_skip_converged_second_stage),
            ("ba_drop_undetermined_points", ba_drop_undetermined_points),
            ("ba_predict_convergence", ba_predict_convergence),
            ("ba_gauss_newton", ba_gauss_newton),
            ("ba_fix_scale_gauge", ba_fix_scale_gauge),
        ):
            if not isinstance(flag, bool):
                raise ConfigError(f"optimizer.{key} = {flag!r}: expected true or false")
        self.lambda_initial = float(lambda_initial)
        self.lambda_factor = float(lambda_factor)
        self.lambda_upper_bound = float(lambda_upper_bound)
        self.ba_lambda_lower_bound = float(ba_lambda_lower_bound)
        self.relative_error_tol = float(relative_error_tol)
        self.absolute_error_tol = float(absolute_error_tol)
        self.fixed_sigma = float(fixed_sigma)
        self.ordering = ordering
        self.linear_solver = linear_solver
        self.ba_ordering = ba_ordering
        self.ba_linear_solver = ba_linear_solver
        self.ba_robust_second_stage = ba_robust_second_stage
        self.use_fixed_lambda_factor = use_fixed_lambda_factor
        self.ba_skip_converged_second_stage = ba_skip_converged_second_stage
        self.ba_drop_undetermined_points = ba_drop_undetermined_points
        self.ba_predict_convergence = ba_predict_convergence
        self.ba_gauss_newton = ba_gauss_newton
        self.ba_chord_test_below = float(ba_chord_test_below)
        self.ba_fix_scale_gauge = ba_fix_scale_gauge

    # ---- LM driver ----------------------------------------------------------------------------------

    def _params(self) -> gtsam.LevenbergMarquardtParams:
        """LM parameters of the config (ordering type and linear solver: the non-BA problems' settings)."""
        params = gtsam.LevenbergMarquardtParams()
        params.setlambdaInitial(self.lambda_initial)
        params.setlambdaFactor(self.lambda_factor)
        params.setlambdaUpperBound(self.lambda_upper_bound)
        params.setRelativeErrorTol(self.relative_error_tol)
        params.setAbsoluteErrorTol(self.absolute_error_tol)
        params.setOrderingType(self.ordering)
        params.setLinearSolverType(self.linear_solver)
        params.setUseFixedLambdaFactor(self.use_fixed_lambda_factor)
        return params

    def _run(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        iterations: int,
        abort: AbortToken | None = None,
        params: gtsam.LevenbergMarquardtParams | None = None,
        predict: bool = False,
    ) -> _LmRun:
        """Up to ``iterations`` LM iterations, checking ``abort`` before each and stopping at convergence
        (GTSAM's own test: relative or absolute decrease below tolerance, or no decrease). ``params``: LM
        parameters (default: ``_params()``).

        ``predict``: also stop when the decrease still to come, extrapolated from the last two, is below the
        relative tolerance. Decreases d_(i-1) then d_i with ratio r = d_i / d_(i-1) < 1 (LM near a minimum
        converges at least linearly, Gauss-Newton quadratically on small residuals) leave at most the geometric
        tail d_i r / (1 - r): when it is below ``relative_error_tol`` times the cost, the next iteration would
        meet GTSAM's test, so it is not run (it would cost a linearization and an elimination to confirm a
        decrease GTSAM then ignores)."""
        if iterations <= 0 or graph.size() == 0:
            return _LmRun(values, 0, bool(abort is not None and abort.is_set()), iterations <= 0)
        if params is None:
            params = self._params()
        params.setMaxIterations(iterations)
        opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        previous = opt.error()
        last_decrease = math.inf
        done = 0
        converged = False
        while done < iterations:
            if abort is not None and abort.is_set():
                return _LmRun(opt.values(), done, True)
            opt.iterate()
            done += 1
            current = opt.error()
            decrease = previous - current
            if decrease <= 0.0 or decrease < self.absolute_error_tol or decrease < self.relative_error_tol * previous:
                converged = True
                break
            ratio = decrease / last_decrease  # 0 after the first iteration: no extrapolation from one decrease
            if predict and 0.0 < ratio < 1.0 and decrease * ratio / (1.0 - ratio) < self.relative_error_tol * current:
                converged = True
                break
            previous, last_decrease = current, decrease
        return _LmRun(opt.values(), done, False, converged)

    def _run_ba(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        iterations: int,
        abort: AbortToken | None,
        params: gtsam.LevenbergMarquardtParams,
        ordering: gtsam.Ordering | None,
        determined: bool,
    ) -> _LmRun:
        """One BA stage: the Gauss-Newton driver (``_gauss_newton``) when ``ba_gauss_newton`` is on, the stage is
        ``determined`` (gauge fixed, every free point with 3 residual rows: the undamped normal equations are
        positive definite) and an explicit elimination ``ordering`` is given; GTSAM's LM (``_run``) otherwise,
        and for whatever iterations remain when the driver gives up (indefinite system or a step that increases
        the cost)."""
        if not (self.ba_gauss_newton and determined and ordering is not None) or self.ba_predict_convergence:
            return self._run(graph, values, iterations, abort, params, self.ba_predict_convergence)
        run = self._gauss_newton(graph, values, iterations, abort, ordering)
        if run.converged or run.aborted or run.iterations >= iterations:
            return run
        rest = self._run(graph, run.values, iterations - run.iterations, abort, params)
        return _LmRun(rest.values, run.iterations + rest.iterations, rest.aborted, rest.converged)

    def _gauss_newton(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        iterations: int,
        abort: AbortToken | None,
        ordering: gtsam.Ordering,
    ) -> _LmRun:
        """Up to ``iterations`` Gauss-Newton iterations of a BA stage whose gauge is fixed, stopping at GTSAM's
        relative decrease test; returns early, not converged, when a step cannot be taken (the caller's LM goes
        on from the returned values).

        Each iteration: ``linearize`` (A, b at the current values), sequential Cholesky in ``ordering`` (points
        first: the Schur complement g2o forms), back-substitution, retraction, the cost. No damping factors, no
        linearized-error evaluations, no model-fidelity test: LM's damping floor (``ba_lambda_lower_bound``, 1e-5)
        is negligible against a BA Hessian whose gauge is fixed (a point's diagonal grows by (f/z)^2 / sigma^2 per
        observation, ~1e4 for f ~ 500 px at a few metres), and LM takes every step of such a BA at that floor (no
        rejected tries on the room's recorded local BAs), so the steps are LM's to rounding.

        The last, confirming iteration of LM (the one whose decrease falls below ``relative_error_tol``) is
        replaced by a chord step: with the new linearization's gradient g = -A^T b and the previous iteration's
        Cholesky factor R (R^T R = H at the previous values), the Gauss-Newton model predicts the decrease
        0.5 |R^-T g|^2 (exact for an unchanged Hessian). When that is below ``relative_error_tol`` times the cost,
        the step -R^-1 R^-T g is taken from the old factor (two triangular solves instead of an elimination) and
        the stage has converged; a step that does not decrease the cost is not taken. The result differs from
        taking a full last iteration only through the Hessian's change over one converged step (second order).
        The test (a gradient and two triangular solves: 2-16 ms on the room's local BAs) runs only after a step whose
        relative decrease was below ``ba_chord_test_below``: after a larger one the next decrease is not yet below
        the tolerance (on the room: relative decreases ~3e-2, ~2e-4, ~2e-6 in the three iterations).
        """
        error = graph.error(values)
        factor: gtsam.GaussianBayesNet | None = None
        last_relative = math.inf
        done = 0
        while done < iterations:
            if abort is not None and abort.is_set():
                return _LmRun(values, done, True)
            linear = graph.linearize(values)
            if factor is not None and last_relative < self.ba_chord_test_below:
                y = factor.backSubstituteTranspose(linear.gradientAtZero())
                if 0.5 * y.dot(y) < self.relative_error_tol * error:
                    step = factor.backSubstitute(y)
                    step.scaleInPlace(-1.0)
                    chord = values.retract(step)
                    done += 1
                    if graph.error(chord) <= error:
                        values = chord
                    return _LmRun(values, done, False, True)
            try:
                factor = linear.eliminateSequential(ordering)
            except RuntimeError:  # indeterminant system (a direction nothing constrains): LM's damping takes over
                return _LmRun(values, done, False)
            moved = values.retract(factor.optimize())
            current = graph.error(moved)
            if not current <= error:  # a step up (or NaN): LM from here
                return _LmRun(values, done, False)
            values = moved
            done += 1
            decrease = error - current
            last_relative = decrease / error if error > 0.0 else 0.0
            error = current
            if decrease < self.absolute_error_tol or last_relative < self.relative_error_tol:
                return _LmRun(values, done, False, True)
        return _LmRun(values, done, False)

    # ---- noise models -------------------------------------------------------------------------------

    @staticmethod
    def _models(dim: int, levels: int, scale_factor: float, delta2: float, robust: bool) -> list[gtsam.noiseModel.Base]:
        """Isotropic models of sigma = scale_factor^level (px), Huber-wrapped (delta = sqrt(chi2 gate)) if robust."""
        out: list[gtsam.noiseModel.Base] = []
        for level in range(levels):
            base = gtsam.noiseModel.Isotropic.Sigma(dim, scale_factor**level)
            if robust:
                huber = gtsam.noiseModel.mEstimator.Huber.Create(math.sqrt(delta2))
                out.append(gtsam.noiseModel.Robust.Create(huber, base))
            else:
                out.append(base)
        return out

    # ---- reprojection graphs ------------------------------------------------------------------------

    def _reprojection_graph(
        self,
        active: B,
        pose_of_obs: I64,
        point_key_of_obs: I64,
        uv: F64,
        u_right: F64,
        level: I64,
        intrinsics: F64,
        bf: F64,
        pose_key0: int,
        scale_factor: float,
        chi2_mono: float,
        chi2_stereo: float,
        robust: bool,
        fisheye: F64 | None = None,
    ) -> gtsam.NonlinearFactorGraph:
        """Projection (mono) and stereo factors of the active observations.

        pose_of_obs: (E,) pose index (key pose_key0 + index); point_key_of_obs: (E,) point keys; intrinsics (P, 4)
        and bf (P,) per pose; fisheye: (P, 4) Kannala-Brandt k1..k4 per pose (raw fisheye observations), or None.
        """
        graph = gtsam.NonlinearFactorGraph()
        levels = int(level.max()) + 1 if len(level) else 1
        mono_models = self._models(2, levels, scale_factor, chi2_mono, robust)
        stereo_models = self._models(3, levels, scale_factor, chi2_stereo, robust)
        stereo = np.isfinite(u_right)
        mono = active & ~stereo
        if fisheye is not None:
            self._add_fisheye_factors(
                graph, mono, pose_of_obs, point_key_of_obs, uv, level, intrinsics, fisheye, pose_key0, mono_models
            )
            mono = np.zeros_like(mono)
        cal: dict[int, gtsam.Cal3_S2] = {}
        # Group mono observations by (pose, level) and insert each group in one C++ call.
        idx = np.flatnonzero(mono)
        if len(idx):
            group = pose_of_obs[idx] * levels + level[idx]
            order = np.argsort(group, kind="stable")
            idx = idx[order]
            group = group[order]
            bounds = np.flatnonzero(np.r_[True, group[1:] != group[:-1], True])
            for a, b in itertools.pairwise(bounds):
                sel = idx[a:b]
                pose = int(pose_of_obs[sel[0]])
                K = cal.get(pose)
                if K is None:
                    fx, fy, cx, cy = intrinsics[pose]
                    K = cal[pose] = gtsam.Cal3_S2(fx, fy, 0.0, cx, cy)
                gtsam.utilities.insertProjectionFactors(
                    graph,
                    pose_key0 + pose,
                    point_key_of_obs[sel].astype(np.float64),
                    np.ascontiguousarray(uv[sel].T),
                    mono_models[int(level[sel[0]])],
                    K,
                )
        cal_stereo: dict[int, gtsam.Cal3_S2Stereo] = {}
        for e in np.flatnonzero(active & stereo):
            pose = int(pose_of_obs[e])
            Ks = cal_stereo.get(pose)
            if Ks is None:
                fx, fy, cx, cy = intrinsics[pose]
                Ks = cal_stereo[pose] = gtsam.Cal3_S2Stereo(fx, fy, 0.0, cx, cy, float(bf[pose]) / fx)
            graph.add(
                gtsam.GenericStereoFactor3D(
                    gtsam.StereoPoint2(uv[e, 0], u_right[e], uv[e, 1]),
                    stereo_models[int(level[e])],
                    pose_key0 + pose,
                    int(point_key_of_obs[e]),
                    Ks,
                )
            )
        return graph

    @staticmethod
    def _add_fisheye_factors(
        graph: gtsam.NonlinearFactorGraph,
        mono: B,
        pose_of_obs: I64,
        point_key_of_obs: I64,
        uv: F64,
        level: I64,
        intrinsics: F64,
        fisheye: F64,
        pose_key0: int,
        models: list[gtsam.noiseModel.Base],
    ) -> None:
        """One GenericProjectionFactorCal3Fisheye per monocular observation (no batch utility exists for it)."""
        cal: dict[int, gtsam.Cal3Fisheye] = {}
        for e in np.flatnonzero(mono):
            pose = int(pose_of_obs[e])
            K = cal.get(pose)
            if K is None:
                fx, fy, cx, cy = intrinsics[pose]
                K = cal[pose] = gtsam.Cal3Fisheye(fx, fy, 0.0, cx, cy, *(float(c) for c in fisheye[pose]))
            graph.add(
                gtsam.GenericProjectionFactorCal3Fisheye(
                    uv[e], models[int(level[e])], pose_key0 + pose, int(point_key_of_obs[e]), K
                )
            )

    @staticmethod
    def _add_second_camera_factors(
        graph: gtsam.NonlinearFactorGraph,
        active: B,
        pose_of_obs: I64,
        point_key_of_obs: I64,
        uv: F64,
        level: I64,
        intrinsics2: F64,
        fisheye2: F64 | None,
        T_c1_c2: F64,
        pose_key0: int,
        models: list[gtsam.noiseModel.Base],
    ) -> None:
        """One projection factor per active observation of a rig's second camera (ORB-SLAM3
        EdgeSE3ProjectXYZToBody): the body pose is camera 1's (T_w_c1 in the values), the sensor sits at
        body_P_sensor = T_c1_c2 of the observation's keyframe; intrinsics2 (P, 4), fisheye2 (P, 4) k1..k4 or None
        (pinhole), T_c1_c2 (P, 4, 4) per pose."""
        for e in np.flatnonzero(active):
            pose = int(pose_of_obs[e])
            fx, fy, cx, cy = intrinsics2[pose]
            body_P_sensor = pose3_from_T(T_c1_c2[pose])
            if fisheye2 is None:
                graph.add(
                    gtsam.GenericProjectionFactorCal3_S2(
                        uv[e],
                        models[int(level[e])],
                        pose_key0 + pose,
                        int(point_key_of_obs[e]),
                        gtsam.Cal3_S2(fx, fy, 0.0, cx, cy),
                        body_P_sensor,
                    )
                )
            else:
                graph.add(
                    gtsam.GenericProjectionFactorCal3Fisheye(
                        uv[e],
                        models[int(level[e])],
                        pose_key0 + pose,
                        int(point_key_of_obs[e]),
                        gtsam.Cal3Fisheye(fx, fy, 0.0, cx, cy, *(float(c) for c in fisheye2[pose])),
                        body_P_sensor,
                    )
                )

    # ---- motion-only BA -----------------------------------------------------------------------------

    def optimize_pose(self, problem: PoseOnlyProblem) -> PoseOnlyResult:
        """ORB-SLAM PoseOptimization: ``rounds`` rounds of ``iterations_per_round`` LM iterations."""
        validate_pose_problem(problem, supports_rig=True, backend="gtsam")
        n = len(problem.xyz_w)
        second = np.zeros(n, dtype=bool) if problem.camera_index is None else np.asarray(problem.camera_index) == 1
        pose_key = n
        point_noise = gtsam.noiseModel.Isotropic.Sigma(3, self.fixed_sigma)
        base_values = gtsam.Values()
        base_values.insert(pose_key, pose3_from_T(invert_rigid(problem.T_c_w_init)))
        points = gtsam.NonlinearFactorGraph()
        for j in range(n):
            base_values.insertPoint3(j, problem.xyz_w[j])
            points.add(gtsam.PriorFactorPoint3(j, problem.xyz_w[j], point_noise))
        gates = np.where(np.isfinite(problem.u_right_px), problem.chi2_stereo, problem.chi2_mono)
        inlier = np.ones(n, dtype=bool)
        T_c_w = problem.T_c_w_init.copy()
        iterations = 0
        for _ in range(problem.rounds):
            if inlier.sum() < _MIN_POSE_EDGES and iterations > 0:
                break
            graph = self._reprojection_graph(
                inlier & ~second,
                np.zeros(n, dtype=np.int64),
                np.arange(n, dtype=np.int64),
                problem.uv_px,
                problem.u_right_px,
                problem.level,
                problem.intrinsics[None, :],
                np.array([problem.bf]),
                pose_key,
                problem.scale_factor,
                problem.chi2_mono,
                problem.chi2_stereo,
                robust=True,
                fisheye=None if problem.distortion is None else np.asarray(problem.distortion)[None, :],
            )
            if second.any():
                self._add_second_camera_factors(
                    graph,
                    inlier & second,
                    np.zeros(n, dtype=np.int64),
                    np.arange(n, dtype=np.int64),
                    problem.uv_px,
                    problem.level,
                    np.asarray(problem.intrinsics2, np.float64)[None, :],
                    None if problem.distortion2 is None else np.asarray(problem.distortion2, np.float64)[None, :],
                    invert_rigid(np.asarray(problem.T_c2_c1, np.float64))[None, :, :],
                    pose_key,
                    self._models(2, int(problem.level.max()) + 1, problem.scale_factor, problem.chi2_mono, True),
                )
            graph.push_back(points)
            # Each round restarts from the initial pose (ORB-SLAM resets the vertex estimate per round).
            run = self._run(graph, gtsam.Values(base_values), problem.iterations_per_round)
            iterations += run.iterations
            T_c_w = invert_rigid(run.values.atPose3(pose_key).matrix())
            inlier = pose_chi2(problem, T_c_w) <= gates
        return PoseOnlyResult(
            T_c_w=T_c_w,
            inliers=inlier,
            cost_initial=pose_cost(problem, problem.T_c_w_init),
            cost_final=pose_cost(problem, T_c_w, inlier),
            iterations=iterations,
        )

    # ---- bundle adjustment --------------------------------------------------------------------------

    def bundle_adjust(self, problem: BundleProblem, abort: AbortToken | None = None) -> BundleResult:
        """ORB-SLAM local/global BA: iterations_first, outlier pass, iterations_second; stops at ``abort``.

        As ORB-SLAM2's LocalBundleAdjustment, the second stage runs without the Huber kernel
        (``ba_robust_second_stage``, default false). Elimination: ``ba_ordering`` / ``ba_linear_solver``.
        """
        validate_bundle_problem(problem, supports_rig=True, backend="gtsam")
        K, M = len(problem.T_c_w), len(problem.xyz_w)
        E = len(problem.obs_pose)
        second = np.zeros(E, dtype=bool) if problem.camera_index is None else np.asarray(problem.camera_index) == 1
        pose_key0 = M
        values = gtsam.Values()
        T_w_c = invert_rigid(problem.T_c_w)
        for k in range(K):
            values.insert(pose_key0 + k, pose3_from_T(T_w_c[k]))
        for j in range(M):
            values.insertPoint3(j, problem.xyz_w[j])
        priors = gtsam.NonlinearFactorGraph()
        pose_noise = gtsam.noiseModel.Isotropic.Sigma(6, self.fixed_sigma)
        point_noise = gtsam.noiseModel.Isotropic.Sigma(3, self.fixed_sigma)
        for kf in np.flatnonzero(problem.pose_fixed):
            priors.add(gtsam.PriorFactorPose3(pose_key0 + int(kf), pose3_from_T(T_w_c[kf]), pose_noise))
        for pt in np.flatnonzero(problem.point_fixed):
            priors.add(gtsam.PriorFactorPoint3(int(pt), problem.xyz_w[pt], point_noise))

        def graph_of(active: B, robust: bool) -> gtsam.NonlinearFactorGraph:
            g = self._reprojection_graph(
                active & ~second,
                problem.obs_pose,
                problem.obs_point,
                problem.uv_px,
                problem.u_right_px,
                problem.level,
                problem.intrinsics,
                problem.bf,
                pose_key0,
                problem.scale_factor,
                problem.chi2_mono,
                problem.chi2_stereo,
                robust,
                None if problem.distortion is None else np.asarray(problem.distortion),
            )
            if (active & second).any():
                self._add_second_camera_factors(
                    g,
                    active & second,
                    problem.obs_pose,
                    problem.obs_point,
                    problem.uv_px,
                    problem.level,
                    np.asarray(problem.intrinsics2, np.float64),
                    None if problem.distortion2 is None else np.asarray(problem.distortion2, np.float64),
                    invert_rigid(np.asarray(problem.T_c2_c1, np.float64)),
                    pose_key0,
                    self._models(2, int(problem.level.max()) + 1, problem.scale_factor, problem.chi2_mono, robust),
                )
            g.push_back(priors)
            return g

        gates = np.where(np.isfinite(problem.u_right_px), problem.chi2_stereo, problem.chi2_mono)
        points_in = np.ones(M, dtype=bool)
        excluded = np.zeros(E, dtype=bool)
        # The gauge (7 DoF: rotation, translation, scale) is fixed by two fixed keyframes, or by one with stereo
        # observations, a rig's second camera or a fixed point (each fixes the scale): the Gauss-Newton driver's
        # undamped systems are then positive definite. A monocular window with one fixed keyframe (fr1_xyz's usual
        # case) leaves the scale free: ``ba_fix_scale_gauge`` holds it with a range factor (_fix_scale_gauge),
        # otherwise it is left to LM's damping.
        # Every free point also needs 3 residual rows (two monocular observations, or a stereo one): one monocular
        # observation leaves its depth free.
        n_fixed = int(np.count_nonzero(problem.pose_fixed))
        rows = np.where(np.isfinite(problem.u_right_px), 3.0, 2.0)
        metric = bool(np.isfinite(problem.u_right_px).any() or second.any() or problem.point_fixed.any())
        gauge_fixed = n_fixed >= 2 or (n_fixed >= 1 and metric)
        if n_fixed == 1 and not metric and K > 1 and self.ba_fix_scale_gauge:
            gauge_fixed = _fix_scale_gauge(priors, problem.pose_fixed, T_w_c, pose_key0)

        def determined(active: B) -> bool:
            """The gauge is fixed and every free point in the stage has at least 3 residual rows."""
            per_point = np.bincount(problem.obs_point[active], weights=rows[active], minlength=M)
            return gauge_fixed and bool((per_point[points_in & ~problem.point_fixed] >= 3.0).all())

        run = self._run_ba(
            graph_of(np.ones(E, dtype=bool), problem.robust),
            values,
            problem.iterations_first,
            abort,
            *self._ba_params(points_in, pose_key0, K),
            determined(np.ones(E, dtype=bool)),
        )
        iterations = run.iterations

        def estimate(values: gtsam.Values, xyz_w: F64) -> tuple[F64, F64]:
            """Poses and points of ``values`` (into ``xyz_w`` where present); fixed variables exactly as given
            (the priors move them by ~fixed_sigma)."""
            T_c_w, xyz = self._extract(values)
            xyz_w[points_in] = xyz
            T_c_w[problem.pose_fixed] = problem.T_c_w[problem.pose_fixed]
            xyz_w[problem.point_fixed] = problem.xyz_w[problem.point_fixed]
            return T_c_w, xyz_w

        T_c_w, xyz_w = estimate(run.values, np.empty((M, 3)))
        chi2 = bundle_chi2(problem, T_c_w, xyz_w)
        if not run.aborted and problem.iterations_second > 0:
            # chi2 is inf behind the camera: the gate also drops ORB-SLAM's !isDepthPositive() edges
            excluded = ~(chi2 <= gates)
            # Nothing set aside after a converged first stage: every observation passes its gate, so it lies in the
            # quadratic zone of its Huber kernel (delta^2 = the gate), where the kernel-free second stage's cost
            # equals the first stage's. The second stage would optimize the function LM just declared converged
            # (one more LM iteration whose decrease is below relative_error_tol): skipped
            # (``ba_skip_converged_second_stage``).
            same_problem = not excluded.any() and run.converged
            if not (same_problem and self.ba_skip_converged_second_stage):
                active = ~excluded
                # Points left without an active observation keep their estimate and leave the problem. So do, with
                # ``ba_drop_undetermined_points``, points left with one monocular (pinhole, first camera)
                # observation: 2 residual rows for 3 coordinates, nothing fixes their depth along the ray, LM's
                # damping alone keeps the system positive definite, and GTSAM's Cholesky fails at the damping floor
                # (every LM iteration then pays a rejected try, a full elimination, and a x10 damping). Such a point
                # absorbs its 2 residuals, so it adds nothing to the poses: the stage's poses are those with the
                # point in it. Afterwards it is placed where LM would take it, on its observation's ray at its
                # depth in that camera (_place_on_rays): reprojection error zero, as ORB-SLAM2's g2o stage leaves it.
                per_point = np.bincount(problem.obs_point[active], weights=rows[active], minlength=M)
                placeable = active & _pinhole_first_camera(problem) & (rows == 2.0)
                single = (per_point == 2.0) & ~problem.point_fixed & self.ba_drop_undetermined_points
                single &= np.bincount(problem.obs_point[placeable], minlength=M) == 1
                observed = (per_point > 0.0) & ~single
                points_in = observed | problem.point_fixed
                stage2 = run.values
                for pt in np.flatnonzero(~points_in):
                    stage2.erase(int(pt))
                active &= observed[problem.obs_point]
                run = self._run_ba(
                    graph_of(active, problem.robust and self.ba_robust_second_stage),
                    stage2,
                    problem.iterations_second,
                    abort,
                    *self._ba_params(points_in, pose_key0, K),
                    determined(active),
                )
                iterations += run.iterations
                T_c_w, xyz_w = estimate(run.values, xyz_w)
                _place_on_rays(problem, T_c_w, xyz_w, np.flatnonzero(placeable & single[problem.obs_point]))
                chi2 = bundle_chi2(problem, T_c_w, xyz_w)
        # ORB-SLAM2 LocalBundleAdjustment erases an edge whose chi2 fails after the second stage; an edge the outlier
        # pass set to level 1 keeps its stage-1 chi2 (g2o computes errors of active edges only), so it is erased too:
        # the excluded observations stay outliers (the default backend does the same).
        outlier = excluded | ~(chi2 <= gates)
        rho = huber_cost(chi2, gates) if problem.robust else chi2
        return BundleResult(
            T_c_w=T_c_w,
            xyz_w=xyz_w,
            outlier=outlier,
            cost_initial=bundle_cost(problem, problem.T_c_w, problem.xyz_w),
            cost_final=float(rho[~outlier].sum()),
            iterations=iterations,
            aborted=run.aborted,
        )

    def _ba_params(
        self, points_in: B, pose_key0: int, n_poses: int
    ) -> tuple[gtsam.LevenbergMarquardtParams, gtsam.Ordering | None]:
        """LM parameters of a bundle adjustment: ``ba_linear_solver`` and ``ba_ordering``; "SCHUR" eliminates every
        point present (keys where ``points_in``) before the poses (keys pose_key0..pose_key0+n_poses-1): each
        point is eliminated onto the keyframes observing it and the poses are solved last, the reduced camera
        system g2o's and Ceres' Schur solvers form (ORB-SLAM marks points marginalized in g2o the same way).
        Also returns that ordering when the Gauss-Newton driver can use it (SCHUR with sequential Cholesky, whose
        Bayes net gives the chord step's triangular solves), else None."""
        params = self._params()
        params.setLinearSolverType(self.ba_linear_solver)
        params.setlambdaLowerBound(self.ba_lambda_lower_bound)
        if self.ba_ordering != "SCHUR":
            params.setOrderingType(self.ba_ordering)
            return params, None
        ordering = gtsam.Ordering()
        for key in itertools.chain(np.flatnonzero(points_in).tolist(), range(pose_key0, pose_key0 + n_poses)):
            ordering.push_back(key)
        params.setOrdering(ordering)
        return params, ordering if self.ba_linear_solver == "SEQUENTIAL_CHOLESKY" else None

    @staticmethod
    def _extract(values: gtsam.Values) -> tuple[F64, F64]:
        """(K, 4, 4) T_c_w and the (m, 3) points present in ``values``, in key order."""
        T_w_c = poses_from_extract(np.asarray(gtsam.utilities.extractPose3(values)))
        xyz = np.asarray(gtsam.utilities.extractPoint3(values), dtype=np.float64).reshape(-1, 3)
        return invert_rigid(T_w_c), xyz.copy()

    # ---- relative Sim3 ------------------------------------------------------------------------------

    def optimize_sim3(self, problem: Sim3Problem) -> Sim3Result:
        """ORB-SLAM OptimizeSim3: iterations_first, drop matches failing the gate in either direction, then
        iterations_second more (iterations_first again when none was dropped, as ORB-SLAM does)."""
        validate_sim3_problem(problem)
        inv_s1 = problem.scale_factor ** -problem.level1.astype(np.float64)
        inv_s2 = problem.scale_factor ** -problem.level2.astype(np.float64)

        def solve(sel: B, S: F64, iterations: int) -> tuple[F64, int]:
            residual = Sim3MatchesResidual(
                problem.xyz1_c1[sel],
                problem.xyz2_c2[sel],
                problem.uv1_px[sel],
                problem.uv2_px[sel],
                inv_s1[sel],
                inv_s2[sel],
                problem.intrinsics1,
                problem.intrinsics2,
                problem.chi2,
                problem.fix_scale,
                problem.distortion1,
                problem.distortion2,
            )
            graph = gtsam.NonlinearFactorGraph()
            graph.add(make_sim3_factor(0, residual))
            values = gtsam.Values()
            values.insert(0, similarity3_from_S(S))
            run = self._run(graph, values, iterations)
            return S_from_similarity3(run.values.atSimilarity3(0)), run.iterations

        n = len(problem.xyz1_c1)
        keep = np.ones(n, dtype=bool)
        S, iterations = solve(keep, problem.S_12_init, problem.iterations_first)
        e1, e2 = sim3_chi2(problem, S)
        keep = (e1 <= problem.chi2) & (e2 <= problem.chi2)
        more = problem.iterations_second if not keep.all() else problem.iterations_first
        if keep.sum() >= 3:
            S, more_done = solve(keep, S, more)
            iterations += more_done
        e1, e2 = sim3_chi2(problem, S)
        inliers = keep & (e1 <= problem.chi2) & (e2 <= problem.chi2)
        if problem.fix_scale:
            S[:3, :3] /= np.cbrt(np.linalg.det(S[:3, :3]))  # exactly scale 1 (LM kept it; remove rounding)
        return Sim3Result(
            S_12=S,
            inliers=inliers,
            cost_initial=sim3_cost(problem, problem.S_12_init),
            cost_final=sim3_cost(problem, S, inliers),
            iterations=iterations,
        )

    # ---- essential graph ----------------------------------------------------------------------------

    def optimize_essential_graph(self, problem: EssentialGraphProblem) -> EssentialGraphResult:
        """Pose graph over the inverse poses X_k = S_w_k: BetweenFactor(X_j, X_i, S_ij^-1) has error
        Log(S_ij S_jw S_iw^-1), ORB-SLAM's EdgeSim3 error; identity information scaled by the weights."""
        validate_essential_graph_problem(problem)
        Kn = len(problem.S_c_w)
        E = len(problem.edge_i)
        sim3 = problem.use_sim3
        dim = 7 if sim3 else 6
        S_w_c = np.linalg.inv(problem.S_c_w)
        meas_inv = np.linalg.inv(problem.S_ij)
        weights = np.ones(E) if problem.weights is None else np.asarray(problem.weights, dtype=np.float64)
        models: dict[float, gtsam.noiseModel.Base] = {}
        between = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        if sim3:
            for k in range(Kn):
                values.insert(k, similarity3_from_S(S_w_c[k]))
        else:
            for k in range(Kn):
                values.insert(k, pose3_from_T(S_w_c[k]))
        for e in range(E):
            w = float(weights[e])
            model = models.get(w)
            if model is None:
                model = models[w] = gtsam.noiseModel.Isotropic.Sigma(dim, 1.0 / math.sqrt(w))
            i, j = int(problem.edge_i[e]), int(problem.edge_j[e])
            if sim3:
                between.add(gtsam.BetweenFactorSimilarity3(j, i, similarity3_from_S(meas_inv[e]), model))
            else:
                between.add(gtsam.BetweenFactorPose3(j, i, pose3_from_T(meas_inv[e]), model))
        graph = gtsam.NonlinearFactorGraph(between)
        prior_model = gtsam.noiseModel.Isotropic.Sigma(dim, self.fixed_sigma)
        for kf in np.flatnonzero(problem.fixed):
            if sim3:
                graph.add(gtsam.PriorFactorSimilarity3(int(kf), similarity3_from_S(S_w_c[kf]), prior_model))
            else:
                graph.add(gtsam.PriorFactorPose3(int(kf), pose3_from_T(S_w_c[kf]), prior_model))
        cost_initial = 2.0 * between.error(values)
        run = self._run(graph, values, problem.iterations)
        out: F64 = np.empty((Kn, 4, 4))
        if sim3:
            for k in range(Kn):
                out[k] = S_from_similarity3(run.values.atSimilarity3(k))
            out = np.asarray(np.linalg.inv(out), dtype=np.float64)
        else:
            out = invert_rigid(poses_from_extract(np.asarray(gtsam.utilities.extractPose3(run.values))))
        out[problem.fixed] = problem.S_c_w[problem.fixed]
        return EssentialGraphResult(
            S_c_w=out,
            cost_initial=cost_initial,
            cost_final=2.0 * between.error(run.values),
            iterations=run.iterations,
        )


# The range factor's sigma as a fraction of the distance it holds: the reprojection cost does not change along the
# scale direction, so any sigma fixes it; this one keeps the factor's Hessian entry (~1/(1e-3 d)^2) in the range of
# the poses' reprojection terms (~(f/z)^2 per observation), so the Cholesky stays well conditioned.
_SCALE_GAUGE_RELATIVE_SIGMA = 1e-3


def _fix_scale_gauge(priors: gtsam.NonlinearFactorGraph, pose_fixed: B, T_w_c: F64, pose_key0: int) -> bool:
    """Hold the scale gauge of a monocular BA with one fixed keyframe; returns whether it could.

    With one fixed keyframe (centre c0) and no metric observation (stereo, depth, a rig's extrinsic, a fixed point),
    scaling every free camera centre and point about c0 by s > 0 leaves every reprojection unchanged: the normal
    equations are singular along s. LM's damping alone keeps it finite and lets it drift while the points outside
    the window keep the old scale (fr1_xyz's young map: one GTSAM local BA shrank it to 0.52x and tracking was lost
    at frame 28; docs/BENCHMARKS.md, session 17). A range factor holds the distance from c0 to the free keyframe
    farthest from it at its current value: the constrained minimum has the cost of the unconstrained one (it is
    the same solution up to the gauge), and the undamped system is definite, so the Gauss-Newton driver runs.
    Returns False (nothing added) when every free centre coincides with c0 (no distance to hold).
    """
    fixed = int(np.flatnonzero(pose_fixed)[0])
    free = np.flatnonzero(~pose_fixed)
    distance = np.linalg.norm(T_w_c[free, :3, 3] - T_w_c[fixed, :3, 3], axis=1)
    farthest = int(np.argmax(distance))
    d = float(distance[farthest])
    if not (math.isfinite(d) and d > 0.0):
        return False
    model = gtsam.noiseModel.Isotropic.Sigma(1, _SCALE_GAUGE_RELATIVE_SIGMA * d)
    priors.add(gtsam.RangeFactorPose3(pose_key0 + fixed, pose_key0 + int(free[farthest]), d, model))
    return True


def _pinhole_first_camera(problem: BundleProblem) -> B:
    """(E,) observations made through a pinhole camera 0 (the model _place_on_rays inverts)."""
    E = len(problem.obs_pose)
    if problem.distortion is not None:
        return np.zeros(E, dtype=bool)
    if problem.camera_index is None:
        return np.ones(E, dtype=bool)
    return np.asarray(problem.camera_index) == 0


def _place_on_rays(problem: BundleProblem, T_c_w: F64, xyz_w: F64, obs: I64) -> None:
    """Move each point of the observations ``obs`` (one each, pinhole camera 0) to the closest point of its pixel's
    ray, in place in ``xyz_w`` (M, 3) with the poses T_c_w (K, 4, 4): the reprojection error becomes zero with the
    smallest move, perpendicular to the ray (the null space of the projection's Jacobian), where LM's damped
    minimum-norm steps take a point with one observation. Points behind the camera stay."""
    if not len(obs):
        return
    k, j = problem.obs_pose[obs], problem.obs_point[obs]
    R, t = T_c_w[k, :3, :3], T_c_w[k, :3, 3]
    pc = np.einsum("nij,nj->ni", R, xyz_w[j]) + t
    fx, fy, cx, cy = (problem.intrinsics[k, c] for c in range(4))
    ray = np.stack([(problem.uv_px[obs, 0] - cx) / fx, (problem.uv_px[obs, 1] - cy) / fy, np.ones(len(obs))], axis=1)
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    along = np.einsum("ni,ni->n", pc, ray)
    ahead = (pc[:, 2] > 0.0) & (along > 0.0)
    moved = np.einsum("nji,nj->ni", R, along[:, None] * ray - t)  # R^T (pc' - t)
    xyz_w[j[ahead]] = moved[ahead]


def reference_bundle_adjust(problem: BundleProblem) -> BundleResult:
    """The bare GTSAM script (slamkit_gtsam.bare) on ``problem``, as a BundleResult (for benchmarks)."""
    from slamkit_gtsam.bare import bare_bundle_adjust

    T_c_w, xyz_w, iterations, dropped = bare_bundle_adjust(problem)
    gates = np.where(np.isfinite(problem.u_right_px), problem.chi2_stereo, problem.chi2_mono)
    outlier = dropped | ~(bundle_chi2(problem, T_c_w, xyz_w) <= gates)  # ORB-SLAM2's rule, as the backend's
    return BundleResult(
        T_c_w=T_c_w,
        xyz_w=xyz_w,
        outlier=outlier,
        cost_initial=bundle_cost(problem, problem.T_c_w, problem.xyz_w),
        cost_final=bundle_cost(problem, T_c_w, xyz_w, ~outlier),
        iterations=iterations,
    )
