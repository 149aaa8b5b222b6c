"""Entry point of the slamkit_gtsam plugin: declares the GTSAM optimizer and its default config node.

Paper constants (chi-square gates and Huber deltas sqrt(5.991) / sqrt(7.815), the 4 x 10 iterations of motion-only
BA, 5 + 10 of local BA, 20 of the essential graph) travel with each problem (slamkit.problems, filled by the
pipeline from its config); this node holds the solver's own settings.
"""

from __future__ import annotations

from slamkit.hookspecs import ComponentSpec, hookimpl


@hookimpl
def slamkit_components() -> list[ComponentSpec]:
    return [
        ComponentSpec(
            kind="optimizer",
            name="gtsam",
            target="slamkit_gtsam.backend.GtsamOptimizer",
            config={
                "worker": "inline",  # inline | process: run the backend in a worker process (slamkit.optim.worker)
                "lambda_initial": 1e-5,  # LM initial damping (GTSAM default; g2o/ORB-SLAM start lower, 1e-16 in EG)
                "lambda_factor": 10.0,  # LM damping multiplier on a rejected step (GTSAM default)
                "lambda_upper_bound": 1e5,  # LM gives up an iteration beyond this damping (GTSAM default)
                "use_fixed_lambda_factor": True,  # GTSAM's x10 / /10 damping rule (false: g2o's Nielsen rule)
                "relative_error_tol": 1e-5,  # stop early when the cost decreases less than this, relatively (GTSAM)
                "absolute_error_tol": 0.0,  # ... or absolutely (0: pose-graph costs are tiny; GTSAM uses 1e-5)
                "fixed_sigma": 1e-8,  # prior sigma holding fixed variables (their output is the exact input)
                "ordering": "COLAMD",  # elimination ordering of pose, Sim3 and pose-graph problems: COLAMD | METIS
                "linear_solver": "MULTIFRONTAL_CHOLESKY",  # their linear solver (GTSAM's LM default)
                # Bundle adjustment (docs/BENCHMARKS.md "Optimizer backends", real local BAs of the room):
                "ba_ordering": "SCHUR",  # points first, then poses (g2o's/ORB-SLAM's marginalized points) | COLAMD | METIS
                "ba_linear_solver": "SEQUENTIAL_CHOLESKY",  # measured faster than multifrontal with SCHUR
                # ORB-SLAM2 LocalBundleAdjustment: setRobustKernel(0) on every edge after the outlier pass
                "ba_robust_second_stage": False,
                # BA's LM never damps below this (GTSAM's default 0): a monocular local BA with one fixed keyframe
                # leaves the scale gauge free; at lambda ~1e-7 its Cholesky fails and the try is wasted
                "ba_lambda_lower_bound": 1e-5,
                # BA: no second LM run when the first converged and the outlier pass set nothing aside (every
                # observation inside its gate, so inside its Huber kernel's quadratic zone: the kernel-free second
                # stage has the first stage's cost; ORB-SLAM2's 10 more g2o iterations would not move it either)
                "ba_skip_converged_second_stage": True,
                # BA's second stage: a point left with fewer residual rows than coordinates (one monocular
                # observation) keeps its first-stage estimate and leaves the problem (its depth is unconstrained;
                # GTSAM's Cholesky fails on it at the damping floor and LM pays a rejected try per iteration)
                "ba_drop_undetermined_points": True,
                # true: BA's LM also stops when the decrease still to come, extrapolated from the last two decreases
                # as a geometric tail, is below relative_error_tol (one iteration fewer per local BA on the room,
                # 0.69x time); off: fr1_xyz's seed-0 ATE went from 1.00 to 3.68 cm with it (docs/BENCHMARKS.md, gtsam2)
                "ba_predict_convergence": False,
                # BA stages whose gauge is fixed (two fixed keyframes, or one with stereo observations) run a
                # Gauss-Newton driver instead of GTSAM's LM (same steps: LM takes them all at its damping floor),
                # whose last, confirming iteration is a chord step on the previous Cholesky factor when the
                # predicted decrease is below relative_error_tol (docs/BENCHMARKS.md, branch gtsamba)
                "ba_gauss_newton": True,
                # ... that prediction is tested only after a step whose relative decrease was below this (room's
                # local BAs: ~3e-2, ~2e-4, ~2e-6 in three iterations; the test costs a gradient and two solves)
                "ba_chord_test_below": 1e-3,
                # A monocular BA with one fixed keyframe: a range factor holds the distance from it to the farthest
                # free keyframe (the scale gauge, which reprojection leaves free; LM's damping let it drift to 0.52x
                # on fr1_xyz's young map and tracking was lost: docs/BENCHMARKS.md, session 17/18). The stage is
                # then determined and runs the Gauss-Newton driver
                "ba_fix_scale_gauge": True,
            },
            description="GTSAM 4 (projection/stereo factors, Similarity3 pose graph, Levenberg-Marquardt)",
        )
    ]
