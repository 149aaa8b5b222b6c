"""Motion-only bundle adjustment (ORB-SLAM Optimizer::PoseOptimization) with a 6x6 LM.

ORB-SLAM runs ``rounds`` optimizations of ``iterations_per_round`` LM iterations. Each round starts again
from the initial pose, optimizes over the observations currently classified as inliers, then re-classifies
every observation with the chi-square gate (5.991 mono, 7.815 stereo), so an outlier of one round can come
back in the next. The Huber kernel is dropped from the third round on (ORB-SLAM: ``if(it==2)
e->setRobustKernel(0)``). A point behind the camera is an outlier whatever its chi2.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slamkit.problems import CAMERA_KANNALA_BRANDT, PoseOnlyProblem, PoseOnlyResult
from slamkit_scipy.lie import se3_exp_batch
from slamkit_scipy.lm import LMSettings, levenberg_marquardt
from slamkit_scipy.reprojection import (
    Observations,
    chi2_of,
    make_observations,
    pose_jacobian,
    projection_jacobian,
    residuals,
)
from slamkit_scipy.rig_kernels import rig_chi2, rig_linearize
from slamkit_scipy.robust import huber_cost, huber_weight, inv_sigma2

F64 = NDArray[np.float64]


def _camera_points(T: F64, X: F64) -> F64:
    out: F64 = X @ T[:3, :3].T + T[:3, 3]
    return out


def robust_cost(T: F64, X: F64, obs: Observations, robust: bool) -> float:
    """Sum of Huber (or plain) chi2 of the observations at pose T (4, 4)."""
    chi2 = chi2_of(residuals(_camera_points(T, X), obs), obs)
    return float(np.sum(huber_cost(chi2, obs.delta) if robust else chi2))


def _solve6(system: tuple[F64, F64], lam: float) -> F64:
    H, g = system
    try:
        out: F64 = np.asarray(np.linalg.solve(H + lam * np.eye(6), -g), dtype=np.float64)
    except np.linalg.LinAlgError:
        return np.full(6, np.nan)
    return out


def linearize_pose(T: F64, *, X: F64, obs: Observations, robust: bool) -> tuple[tuple[F64, F64], F64, float, float]:
    """At pose T (4, 4): ((H, g), g, cost, max diag H) with H = sum J^T w J, g = sum J^T w r (6x6, 6),
    w = info * rho'(chi2) (IRLS; d cost / d xi = 2 g exactly), J = d r / d xi for T <- exp(xi) T."""
    p_c = _camera_points(T, X)
    r = residuals(p_c, obs)
    chi2 = chi2_of(r, obs)
    w = obs.info * (huber_weight(chi2, obs.delta) if robust else 1.0)
    J = pose_jacobian(p_c, projection_jacobian(p_c, obs))
    wJ = J * w[:, None, None]
    H = np.einsum("eki,ekj->ij", wJ, J)
    g = np.einsum("eki,ek->i", wJ, r)
    f = float(np.sum(huber_cost(chi2, obs.delta) if robust else chi2))
    return (H, g), g, f, float(np.max(np.diag(H), initial=0.0))


def retract_pose(T: F64, h: F64) -> F64:
    """T (4, 4) <- exp(h) T, h = [omega, v]."""
    out: F64 = se3_exp_batch(h[None, :])[0] @ T
    return out


@dataclass
class _Rig:
    """A pose problem's observations of a two-camera rig as rig_kernels reads them: cam (N, 8), fish (N,),
    Rx (N, 3, 3), tx (N, 3) (the body camera -> observing camera transform per observation)."""

    cam: F64
    fish: NDArray[np.bool_]
    Rx: F64
    tx: F64

    @staticmethod
    def of(problem: PoseOnlyProblem, obs: Observations) -> _Rig | None:
        if problem.camera_index is None or not (np.asarray(problem.camera_index) == 1).any():
            return None
        second = np.asarray(problem.camera_index) == 1
        n = second.size
        cam = obs.cam()
        cam[second, :4] = np.asarray(problem.intrinsics2, np.float64)
        cam[second, 4:] = 0.0 if problem.distortion2 is None else np.asarray(problem.distortion2, np.float64)
        fish = np.full(n, obs.kb is not None)
        fish[second] = problem.camera_model2 == CAMERA_KANNALA_BRANDT
        T21 = np.asarray(problem.T_c2_c1, np.float64)
        Rx = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
        tx = np.zeros((n, 3))
        Rx[second] = T21[:3, :3]
        tx[second] = T21[:3, 3]
        return _Rig(cam, fish, Rx, tx)

    def subset(self, keep: NDArray[np.bool_]) -> _Rig:
        return _Rig(self.cam[keep], self.fish[keep], self.Rx[keep], self.tx[keep])

    def chi2_depth(self, T: F64, X: F64, obs: Observations) -> tuple[F64, F64]:
        n = X.shape[0]
        with np.errstate(divide="ignore", invalid="ignore"):
            out: tuple[F64, F64] = rig_chi2(
                np.ascontiguousarray(T[None, :3, :3]),
                np.ascontiguousarray(T[None, :3, 3]),
                np.ascontiguousarray(X),
                np.zeros(n, np.int64),
                np.arange(n, dtype=np.int64),
                obs.uvr,
                obs.stereo,
                obs.intr,
                obs.bf,
                obs.info,
                self.cam,
                self.fish,
                self.Rx,
                self.tx,
            )
        return out

    def cost(self, T: F64, *, X: F64, obs: Observations, robust: bool) -> float:
        chi2, _ = self.chi2_depth(T, X, obs)
        return float(np.sum(huber_cost(chi2, obs.delta) if robust else chi2))

    def linearize(
        self, T: F64, *, X: F64, obs: Observations, robust: bool
    ) -> tuple[tuple[F64, F64], F64, float, float]:
        n = X.shape[0]
        U, _, _, gc, _, f = rig_linearize(
            np.ascontiguousarray(T[None, :3, :3]),
            np.ascontiguousarray(T[None, :3, 3]),
            np.ascontiguousarray(X),
            np.zeros(n, np.int64),
            np.arange(n, dtype=np.int64),
            np.zeros(n, np.int64),
            np.full(n, -1, np.int64),
            obs.uvr,
            obs.stereo,
            obs.intr,
            obs.bf,
            obs.info,
            obs.delta,
            robust,
            1,
            0,
            self.cam,
            self.fish,
            self.Rx,
            self.tx,
        )
        H, g = U[0], gc[0]
        return (H, g), g, float(f), float(np.max(np.diag(H), initial=0.0))


class _OneCamera:
    """The pose's observations all in the problem's one camera: the same interface as _Rig, on the one-camera
    residuals (slamkit_scipy.reprojection), so optimize_pose runs one loop of rounds for both."""

    def subset(self, keep: NDArray[np.bool_]) -> _OneCamera:
        return self

    def chi2_depth(self, T: F64, X: F64, obs: Observations) -> tuple[F64, F64]:
        """(chi2 (N,), depth (N,) m in the camera) at pose T."""
        p_c = _camera_points(T, X)
        return chi2_of(residuals(p_c, obs), obs), p_c[:, 2]

    def linearize(
        self, T: F64, *, X: F64, obs: Observations, robust: bool
    ) -> tuple[tuple[F64, F64], F64, float, float]:
        return linearize_pose(T, X=X, obs=obs, robust=robust)

    def cost(self, T: F64, *, X: F64, obs: Observations, robust: bool) -> float:
        return robust_cost(T, X, obs, robust)


def optimize_pose(problem: PoseOnlyProblem, settings: LMSettings, stop_behind: bool = True) -> PoseOnlyResult:
    """Solve a validated PoseOnlyProblem; see the module docstring for ORB-SLAM's round structure. Observations of a
    rig's second camera (``camera_index`` 1) go through slamkit_scipy.rig_kernels."""
    n = problem.xyz_w.shape[0]
    X_all = np.asarray(problem.xyz_w, dtype=np.float64)
    intr = np.broadcast_to(np.asarray(problem.intrinsics, dtype=np.float64), (n, 4))
    obs_all = make_observations(
        np.asarray(problem.uv_px, dtype=np.float64),
        np.asarray(problem.u_right_px, dtype=np.float64),
        intr,
        np.full(n, float(problem.bf)),
        inv_sigma2(np.asarray(problem.level), problem.scale_factor),
        problem.chi2_mono,
        problem.chi2_stereo,
        None if problem.distortion is None else np.broadcast_to(np.asarray(problem.distortion, np.float64), (n, 4)),
    )
    T0 = np.array(problem.T_c_w_init, dtype=np.float64)
    model_all: _Rig | _OneCamera = _Rig.of(problem, obs_all) or _OneCamera()
    cost_initial = model_all.cost(T0, X=X_all, obs=obs_all, robust=True)
    inlier = np.ones(n, dtype=bool)
    T = T0
    total_iters = 0
    for it in range(problem.rounds):
        robust = it < 2
        X = X_all[inlier]
        obs = obs_all.subset(inlier)
        model = model_all.subset(inlier)
        outcome = levenberg_marquardt(
            T0.copy(),  # every round restarts from the initial pose (ORB-SLAM resets vSE3's estimate)
            functools.partial(model.linearize, X=X, obs=obs, robust=robust),
            _solve6,
            retract_pose,
            functools.partial(model.cost, X=X, obs=obs, robust=robust),
            problem.iterations_per_round,
            settings,
        )
        T = outcome.x
        total_iters += outcome.iterations
        chi2, depth = model_all.chi2_depth(T, X_all, obs_all)  # depth in the observing camera
        inlier = chi2 <= obs_all.chi2_max
        if stop_behind:
            inlier &= depth > 0.0
        if not np.any(inlier):
            break
    cost_final = model_all.subset(inlier).cost(T, X=X_all[inlier], obs=obs_all.subset(inlier), robust=True)
    return PoseOnlyResult(
        T_c_w=T, inliers=inlier, cost_initial=cost_initial, cost_final=cost_final, iterations=total_iters
    )
