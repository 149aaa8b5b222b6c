"""A bare GTSAM local BA: the reference the plugin's overhead is measured against (``slamkit bench optimizer``).

The straight script anyone would write: one factor per observation in a Python loop (projection or stereo
factor, Huber, sigma = scale_factor^level), priors on fixed keyframes, ``LevenbergMarquardtOptimizer.optimize()``
for iterations_first, drop observations failing the chi-square gate, optimize iterations_second more. Same
factors, noise models and LM settings as slamkit_gtsam.backend with its defaults (Huber in the first stage only,
as ORB-SLAM2's LocalBundleAdjustment); none of its machinery (validation, grouped C++ insertion, abort checks,
result costs, the Schur elimination ordering and sequential solver: GTSAM's default COLAMD multifrontal here) nor
its speed rules (GTSAM's own stopping test only; every observed point stays in the second stage).
"""

from __future__ import annotations

import math

import gtsam
import numpy as np
from numpy.typing import NDArray

from slamkit.errors import ProblemError
from slamkit.problems import CAMERA_PINHOLE, BundleProblem

F64 = NDArray[np.float64]


def bare_bundle_adjust(problem: BundleProblem) -> tuple[F64, F64, int, NDArray[np.bool_]]:
    """Run the bare script on ``problem`` -> (T_c_w (K, 4, 4), xyz_w (M, 3), LM iterations done, (E,) observations
    the outlier pass dropped)."""
    if problem.camera_model != CAMERA_PINHOLE:
        raise ProblemError(
            f"BundleProblem.camera_model = {problem.camera_model!r}: the bare GTSAM script models pinhole cameras only"
        )
    K, M = len(problem.T_c_w), len(problem.xyz_w)
    huber_m = gtsam.noiseModel.mEstimator.Huber.Create(math.sqrt(problem.chi2_mono))
    huber_s = gtsam.noiseModel.mEstimator.Huber.Create(math.sqrt(problem.chi2_stereo))
    stereo = np.isfinite(problem.u_right_px)

    levels = int(problem.level.max()) + 1
    mono_models = [
        gtsam.noiseModel.Robust.Create(huber_m, gtsam.noiseModel.Isotropic.Sigma(2, problem.scale_factor**lv))
        for lv in range(levels)
    ]
    stereo_models = [
        gtsam.noiseModel.Robust.Create(huber_s, gtsam.noiseModel.Isotropic.Sigma(3, problem.scale_factor**lv))
        for lv in range(levels)
    ]
    # second stage: no robust kernel (ORB-SLAM2 sets it to 0 on every edge after the outlier pass)
    mono_plain = [gtsam.noiseModel.Isotropic.Sigma(2, problem.scale_factor**lv) for lv in range(levels)]
    stereo_plain = [gtsam.noiseModel.Isotropic.Sigma(3, problem.scale_factor**lv) for lv in range(levels)]
    cals = [gtsam.Cal3_S2(fx, fy, 0.0, cx, cy) for fx, fy, cx, cy in problem.intrinsics]
    cals_stereo = [
        gtsam.Cal3_S2Stereo(fx, fy, 0.0, cx, cy, bf / fx)
        for (fx, fy, cx, cy), bf in zip(problem.intrinsics, problem.bf, strict=True)
    ]

    def build(active: NDArray[np.bool_], robust: bool) -> gtsam.NonlinearFactorGraph:
        graph = gtsam.NonlinearFactorGraph()
        mono = mono_models if robust else mono_plain
        stereo_m = stereo_models if robust else stereo_plain
        for e in np.flatnonzero(active):
            k, j, lv = int(problem.obs_pose[e]), int(problem.obs_point[e]), int(problem.level[e])
            if stereo[e]:
                meas = gtsam.StereoPoint2(problem.uv_px[e, 0], problem.u_right_px[e], problem.uv_px[e, 1])
                graph.add(gtsam.GenericStereoFactor3D(meas, stereo_m[lv], M + k, j, cals_stereo[k]))
            else:
                graph.add(gtsam.GenericProjectionFactorCal3_S2(problem.uv_px[e], mono[lv], M + k, j, cals[k]))
        prior = gtsam.noiseModel.Isotropic.Sigma(6, 1e-8)
        for kf in np.flatnonzero(problem.pose_fixed):
            graph.add(gtsam.PriorFactorPose3(M + int(kf), gtsam.Pose3(np.linalg.inv(problem.T_c_w[kf])), prior))
        return graph

    def lm(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, iterations: int) -> tuple[gtsam.Values, int]:
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(iterations)
        params.setRelativeErrorTol(1e-5)
        params.setAbsoluteErrorTol(0.0)
        opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        result = opt.optimize()
        return result, int(opt.iterations())

    values = gtsam.Values()
    for k in range(K):
        values.insert(M + k, gtsam.Pose3(np.linalg.inv(problem.T_c_w[k])))
    for j in range(M):
        values.insert(j, problem.xyz_w[j])
    values, it1 = lm(
        build(np.ones(len(problem.obs_pose), dtype=bool), problem.robust), values, problem.iterations_first
    )

    def current(vals: gtsam.Values) -> tuple[F64, F64]:
        T = np.stack([np.linalg.inv(vals.atPose3(M + k).matrix()) for k in range(K)])
        return T, np.asarray(gtsam.utilities.extractPoint3(vals), dtype=np.float64).reshape(-1, 3)

    T, xyz = current(values)
    # Outlier pass, vectorised: chi2 of every observation at the current estimate.
    Tk = T[problem.obs_pose]
    pc = np.einsum("nij,nj->ni", Tk[:, :3, :3], xyz[problem.obs_point]) + Tk[:, :3, 3]
    fx, fy, cx, cy = (problem.intrinsics[problem.obs_pose, i] for i in range(4))
    u = fx * pc[:, 0] / pc[:, 2] + cx
    v = fy * pc[:, 1] / pc[:, 2] + cy
    e2 = (problem.uv_px[:, 0] - u) ** 2 + (problem.uv_px[:, 1] - v) ** 2
    ur = u - problem.bf[problem.obs_pose] / pc[:, 2]
    e2 = e2 + np.where(stereo, (problem.u_right_px - ur) ** 2, 0.0)
    chi2 = e2 / problem.scale_factor ** (2.0 * problem.level)
    active = (chi2 <= np.where(stereo, problem.chi2_stereo, problem.chi2_mono)) & (pc[:, 2] > 0)
    observed = np.bincount(problem.obs_point[active], minlength=M) > 0
    active &= observed[problem.obs_point]
    stage2 = gtsam.Values()
    for k in range(K):
        stage2.insert(M + k, values.atPose3(M + k))
    for pt in np.flatnonzero(observed):
        stage2.insert(int(pt), xyz[pt])
    stage2, it2 = lm(build(active, False), stage2, problem.iterations_second)
    T2 = np.stack([np.linalg.inv(stage2.atPose3(M + k).matrix()) for k in range(K)])
    xyz[observed] = np.asarray(gtsam.utilities.extractPoint3(stage2), dtype=np.float64).reshape(-1, 3)
    return T2, xyz, it1 + it2, ~active
