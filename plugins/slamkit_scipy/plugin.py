"""Entry point of the slamkit_scipy plugin: the ``optimizer=scipy`` component and its default config."""

from __future__ import annotations

from slamkit.hookspecs import ComponentSpec, hookimpl


@hookimpl
def slamkit_components() -> list[ComponentSpec]:
    return [
        ComponentSpec(
            kind="optimizer",
            name="scipy",
            target="slamkit_scipy.optimizer.ScipyOptimizer",
            config={
                "worker": "inline",  # inline | process: run the backend in a worker process (slamkit.optim.worker)
                "lm_tau": 1e-5,  # g2o OptimizationAlgorithmLevenberg: initial lambda = tau * max diag(H), tau = 1e-5
                "lm_max_trials": 10,  # g2o OptimizationAlgorithmLevenberg: 10 damped solves per iteration at most
                "lm_rel_tol": 1e-10,  # ours: stop when a step gains < 1e-10 of the cost (g2o runs all iterations)
                "ba_robust_second_stage": False,  # ORB-SLAM LocalBundleAdjustment: setRobustKernel(0) after outliers
                "ba_dense_max": 3000,  # ours: dense Cholesky of the reduced camera system up to 500 free keyframes
                "eg_lambda_init": 1e-16,  # ORB-SLAM OptimizeEssentialGraph: solver->setUserLambdaInit(1e-16)
                "pose_behind_is_outlier": True,  # ours: ORB-SLAM gates only chi2; a point behind the camera is no inlier
            },
            description="numpy/scipy backend: LM with IRLS Huber, Schur-complement BA, sparse Sim3 pose graph",
        )
    ]
