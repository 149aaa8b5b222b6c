"""Bundle adjustment with LM on the Schur complement (ORB-SLAM LocalBundleAdjustment / GlobalBundleAdjustemnt).

Normal equations [[U, W], [W^T, V]] [dc; dp] = -[g_c; g_p] over free poses (6 each, left perturbation
T <- exp(xi) T) and free points (3 each). V is block diagonal (3x3 per point), so the points are eliminated:
the reduced camera system S = U - W V^-1 W^T is solved, then the points are back-substituted.
Up to ``dense_max`` pose parameters (local BA) the blocks, S and the back-substitution come from the numba
kernels of slamkit_scipy.kernels (one pass over observations, one over points, GIL released) and S is
solved by the single-threaded numba Cholesky of the same module (upper triangle, zero blocks skipped);
beyond it (large global BA) V's blocks are inverted in one batched numpy call, S is formed with one
scipy.sparse product and solved with SuperLU.

ORB-SLAM's schedule: ``iterations_first`` LM iterations with the Huber kernel, then every observation
failing its chi-square gate or with the point behind the camera is excluded, then ``iterations_second``
more iterations without the kernel; the final outliers are the excluded observations and those failing
the gate at the end. The abort token is checked before every iteration.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray

from slamkit.interfaces import AbortToken
from slamkit.problems import CAMERA_KANNALA_BRANDT, BundleProblem, BundleResult
from slamkit_scipy.kernels import (
    ba_chi2_depth,
    ba_cost,
    ba_linearize,
    ba_retract,
    ba_solve_dense,
)
from slamkit_scipy.lm import LMSettings, levenberg_marquardt
from slamkit_scipy.reprojection import (
    Observations,
    chi2_of,
    make_observations,
    residuals,
)
from slamkit_scipy.rig_kernels import rig_chi2, rig_cost, rig_linearize
from slamkit_scipy.robust import huber_cost, inv_sigma2

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass
class BAState:
    """T_c_w: (K, 4, 4) poses; xyz_w: (M, 3) m points."""

    T_c_w: F64
    xyz_w: F64


@dataclass
class RigTerms:
    """Per-observation camera of a problem with a two-camera rig (slamkit_scipy.rig_kernels): cam (E, 8) fx, fy, cx,
    cy, k1..k4 of the observing camera; fish (E,) bool, Kannala-Brandt; Rx (E, 3, 3), tx (E, 3): the body camera ->
    observing camera transform (identity for camera 1, T_c2_c1 of the keyframe for camera 2)."""

    cam: F64
    fish: NDArray[np.bool_]
    Rx: F64
    tx: F64

    def subset(self, keep: NDArray[np.int64] | NDArray[np.bool_]) -> RigTerms:
        return RigTerms(
            np.ascontiguousarray(self.cam[keep]),
            np.ascontiguousarray(self.fish[keep]),
            np.ascontiguousarray(self.Rx[keep]),
            np.ascontiguousarray(self.tx[keep]),
        )


def rig_terms(problem: BundleProblem, obs: Observations) -> RigTerms | None:
    """The RigTerms of a problem with second-camera observations (``camera_index`` 1), else None. ``obs`` holds
    camera 1's intrinsics and k1..k4 per observation; the second camera's replace them on its observations."""
    if problem.camera_index is None:
        return None
    second = np.asarray(problem.camera_index) == 1
    if not second.any():
        return None
    obs_pose = np.asarray(problem.obs_pose, dtype=np.int64)
    E = obs_pose.size
    cam = obs.cam()
    k2 = obs_pose[second]
    cam[second, :4] = np.asarray(problem.intrinsics2, np.float64)[k2]
    cam[second, 4:] = 0.0 if problem.distortion2 is None else np.asarray(problem.distortion2, np.float64)[k2]
    fish = np.full(E, obs.kb is not None)
    fish[second] = problem.camera_model2 == CAMERA_KANNALA_BRANDT
    Rx = np.broadcast_to(np.eye(3), (E, 3, 3)).copy()
    tx = np.zeros((E, 3))
    T21 = np.asarray(problem.T_c2_c1, np.float64)[k2]
    Rx[second] = T21[:, :3, :3]
    tx[second] = T21[:, :3, 3]
    return RigTerms(cam, fish, Rx, tx)


def _camera_points(state: BAState, obs_pose: I64, obs_point: I64) -> F64:
    T = state.T_c_w[obs_pose]
    X = state.xyz_w[obs_point]
    out: F64 = np.einsum("eij,ej->ei", T[:, :3, :3], X) + T[:, :3, 3]
    return out


def observation_chi2(
    state: BAState, obs_pose: I64, obs_point: I64, obs: Observations, rig: RigTerms | None = None
) -> tuple[F64, F64]:
    """(E,) chi2 and (E,) depth (m) of every observation at ``state`` (in the camera that saw it, with a rig)."""
    if rig is None and obs.kb is not None:  # one fisheye camera: numpy (the compiled passes are pinhole or rig)
        p_c = _camera_points(state, obs_pose, obs_point)
        with np.errstate(divide="ignore", invalid="ignore"):
            chi2 = chi2_of(residuals(p_c, obs), obs)
        return chi2, p_c[:, 2]
    # the pose, point and observation arrays both compiled passes read (a rig's pass then its second-camera terms)
    common = (
        np.ascontiguousarray(state.T_c_w[:, :3, :3]),
        np.ascontiguousarray(state.T_c_w[:, :3, 3]),
        state.xyz_w,
        obs_pose,
        obs_point,
        obs.uvr,
        obs.stereo,
        obs.intr,
        obs.bf,
        obs.info,
    )
    if rig is None:  # one pinhole camera: the same arithmetic as the numpy path above
        pinhole: tuple[F64, F64] = ba_chi2_depth(*common)
        return pinhole
    with np.errstate(divide="ignore", invalid="ignore"):
        out: tuple[F64, F64] = rig_chi2(*common, rig.cam, rig.fish, rig.Rx, rig.tx)
    return out


class _Stage:
    """Structure of one optimization stage: which observations, poses and points take part."""

    def __init__(
        self,
        problem: BundleProblem,
        obs: Observations,
        active: NDArray[np.bool_],
        robust: bool,
        rig: RigTerms | None = None,
    ) -> None:
        self.robust = robust
        # contiguous and writable, as a fancy-indexed copy is (the compiled kernels' signature)
        self.obs_pose = np.require(problem.obs_pose, np.int64, ["C", "W"])
        self.obs_point = np.require(problem.obs_point, np.int64, ["C", "W"])
        if active.all():  # every observation (the first stage): the arrays as they are, no copies (none is written)
            self.obs = obs
            self.rig = rig
        else:
            e = np.flatnonzero(active)
            self.obs = obs.subset(e)
            self.rig = None if rig is None else rig.subset(e)
            self.obs_pose = self.obs_pose[e]
            self.obs_point = self.obs_point[e]
        # (E, 8) for the fisheye kernels; a pinhole problem's kernels never read it (an empty array of the same type)
        self.cam = self.obs.cam() if self.obs.kb is not None else np.zeros((0, 8))
        K = problem.T_c_w.shape[0]
        M = problem.xyz_w.shape[0]
        # Free poses / points that have at least one active observation get consecutive indices.
        pose_used = np.zeros(K, dtype=bool)
        pose_used[self.obs_pose] = True
        point_used = np.zeros(M, dtype=bool)
        point_used[self.obs_point] = True
        self.free_poses = np.flatnonzero(~np.asarray(problem.pose_fixed, dtype=bool) & pose_used)
        self.free_points = np.flatnonzero(~np.asarray(problem.point_fixed, dtype=bool) & point_used)
        pose_map = np.full(K, -1, dtype=np.int64)
        pose_map[self.free_poses] = np.arange(self.free_poses.size)
        point_map = np.full(M, -1, dtype=np.int64)
        point_map[self.free_points] = np.arange(self.free_points.size)
        self.c = pose_map[self.obs_pose]  # (E,) free pose index or -1
        self.p = point_map[self.obs_point]  # (E,) free point index or -1
        self.nc = self.free_poses.size
        self.np_ = self.free_points.size
        # Observations with both ends free, grouped by point (the numba Schur kernels walk them per point).
        self.both = np.flatnonzero((self.c >= 0) & (self.p >= 0))
        pb = self.p[self.both]
        self.point_obs = self.both[np.argsort(pb, kind="stable")].astype(np.int64)
        self.point_ptr = np.concatenate([[0], np.cumsum(np.bincount(pb, minlength=self.np_))]).astype(np.int64)
        self._w_template: sp.csr_matrix | None = None
        self._w_perm: I64 | None = None

    def _w_pattern(self) -> None:
        """Sparse pattern of W (6 nc x 3 np), one 6x3 block per observation with both ends free (sparse path)."""
        cb, pb = self.c[self.both], self.p[self.both]
        self._w_rows = (6 * cb[:, None, None] + np.arange(6)[None, :, None] + np.zeros((1, 1, 3), np.int64)).ravel()
        self._w_cols = (3 * pb[:, None, None] + np.zeros((1, 6, 1), np.int64) + np.arange(3)[None, None, :]).ravel()
        n = self._w_rows.size
        order = sp.csr_matrix(
            (np.arange(1.0, n + 1.0), (self._w_rows, self._w_cols)), shape=(6 * self.nc, 3 * self.np_)
        )
        order.sum_duplicates()
        # Two observations of one point in one keyframe share a block: then rebuild (summing) every time.
        self._w_perm = (order.data - 1).astype(np.int64) if order.nnz == n else None
        self._w_template = order

    def w_matrix(self, blocks: F64) -> sp.csr_matrix:
        """(B, 6, 3) blocks of the observations with both ends free -> sparse (6 nc, 3 np) matrix."""
        if self._w_template is None:
            self._w_pattern()
        assert self._w_template is not None
        flat = blocks.ravel()
        if self._w_perm is None:
            return sp.csr_matrix((flat, (self._w_rows, self._w_cols)), shape=self._w_template.shape)
        m = self._w_template.copy()
        m.data = flat[self._w_perm]
        return m


@dataclass
class _System:
    U: F64  # (nc, 6, 6)
    V: F64  # (np, 3, 3)
    WT: F64  # (E, 3, 8) per observation W (6 x 3) transposed, lanes 6 and 7 zero (zero unless both ends are free)
    gc: F64  # (nc, 6)
    gp: F64  # (np, 3)


class BundleSolver:
    """LM over one stage (see the module docstring); ``dense_max`` pose parameters use dense Cholesky."""

    def __init__(self, stage: _Stage, dense_max: int) -> None:
        self.st = stage
        self.dense_max = dense_max

    def cost(self, state: BAState) -> float:
        st = self.st
        o = st.obs
        # the arguments both kernels take (as linearize shares them), then each one's camera fields
        args = (
            np.ascontiguousarray(state.T_c_w[:, :3, :3]),
            np.ascontiguousarray(state.T_c_w[:, :3, 3]),
            state.xyz_w,
            st.obs_pose,
            st.obs_point,
            o.uvr,
            o.stereo,
            o.intr,
            o.bf,
            o.info,
            o.delta,
            st.robust,
        )
        if st.rig is not None:
            return float(rig_cost(*args, st.rig.cam, st.rig.fish, st.rig.Rx, st.rig.tx))
        return float(ba_cost(*args, st.cam, o.kb is not None))

    def linearize(self, state: BAState) -> tuple[_System, F64, float, Callable[[], float]]:
        """The LM's linearization at ``state``: (system, g (6 nc + 3 np,), robust cost, max diag(H)); the last is a
        callable, evaluated by the driver at its first linearization only (the initial damping)."""
        st = self.st
        o = st.obs
        shared = (  # the arguments both kernels take; each adds its camera models
            np.ascontiguousarray(state.T_c_w[:, :3, :3]),
            np.ascontiguousarray(state.T_c_w[:, :3, 3]),
            state.xyz_w,
            st.obs_pose,
            st.obs_point,
            st.c,
            st.p,
            o.uvr,
            o.stereo,
            o.intr,
            o.bf,
            o.info,
            o.delta,
            st.robust,
            st.nc,
            st.np_,
        )
        if st.rig is not None:
            U, V, WT, gc, gp, f = rig_linearize(*shared, st.rig.cam, st.rig.fish, st.rig.Rx, st.rig.tx)
        else:
            U, V, WT, gc, gp, f = ba_linearize(*shared, st.cam, o.kb is not None)
        g = np.concatenate([gc.ravel(), gp.ravel()])

        def hmax() -> float:
            return max(
                float(np.max(np.diagonal(U, axis1=1, axis2=2), initial=0.0)),
                float(np.max(np.diagonal(V, axis1=1, axis2=2), initial=0.0)),
            )

        return _System(U, V, WT, gc, gp), g, float(f), hmax

    def solve(self, sys: _System, lam: float) -> F64:
        st = self.st
        n = 6 * st.nc
        if 0 < n <= self.dense_max:
            return ba_solve_dense(sys.U, sys.V, sys.WT, sys.gc, sys.gp, lam, st.c, st.point_ptr, st.point_obs)
        return self._solve_sparse(sys, lam)

    def _solve_sparse(self, sys: _System, lam: float) -> F64:
        """Same Schur complement with scipy.sparse products and SuperLU (large reduced systems)."""
        st = self.st
        nc, npt = st.nc, st.np_
        try:
            Vinv = np.linalg.inv(sys.V + lam * np.eye(3))
        except np.linalg.LinAlgError:
            return np.full(6 * nc + 3 * npt, np.nan)
        if nc == 0:
            dp = -np.einsum("pij,pj->pi", Vinv, sys.gp)
            return dp.ravel()
        Wb = np.ascontiguousarray(sys.WT[st.both, :, :6].transpose(0, 2, 1))  # (B, 6, 3)
        Wm = st.w_matrix(Wb)
        # Y = W V^-1 per observation block (B, 6, 3), same sparsity as W.
        Ym = st.w_matrix(np.matmul(Wb, Vinv[st.p[st.both]]))
        rhs = -sys.gc.ravel() + Ym @ sys.gp.ravel()
        S = sp.csc_matrix(-(Ym @ Wm.T))
        S = S + sp.block_diag(list(sys.U + lam * np.eye(6)), format="csc")
        try:
            dc = spla.splu(sp.csc_matrix(S)).solve(rhs)
        except RuntimeError:  # exactly singular
            return np.full(6 * nc + 3 * npt, np.nan)
        t = -sys.gp.ravel() - Wm.T @ dc
        dp = np.einsum("pij,pj->pi", Vinv, t.reshape(npt, 3))
        return np.concatenate([dc, dp.ravel()])

    def retract(self, state: BAState, h: F64) -> BAState:
        """Left perturbation of the free poses, T <- exp(xi) T, and X <- X + dp for the free points (one compiled
        pass, kernels.ba_retract)."""
        st = self.st
        T, X = ba_retract(state.T_c_w, state.xyz_w, st.free_poses, st.free_points, np.ascontiguousarray(h))
        return BAState(T, X)


def bundle_adjust(
    problem: BundleProblem,
    settings: LMSettings,
    abort: AbortToken | None = None,
    robust_second_stage: bool = False,
    dense_max: int = 3000,
    report_costs: bool = True,
) -> BundleResult:
    """Solve a validated BundleProblem with ORB-SLAM's two-stage schedule (module docstring).

    report_costs: fill the result's cost_initial / cost_final (the robust cost of every observation at the start,
    of the inliers at the end); False leaves them NaN for a caller that computes its own (ScipyOptimizer reports
    slamkit.optim.costs' backend-independent figures), sparing two passes over the observations."""
    obs_pose = np.asarray(problem.obs_pose, dtype=np.int64)
    obs_point = np.asarray(problem.obs_point, dtype=np.int64)
    intr = np.asarray(problem.intrinsics, dtype=np.float64)[obs_pose]
    bf = np.asarray(problem.bf, dtype=np.float64)[obs_pose]
    kb = None if problem.distortion is None else np.asarray(problem.distortion, dtype=np.float64)[obs_pose]
    obs = make_observations(
        np.asarray(problem.uv_px, dtype=np.float64),
        np.asarray(problem.u_right_px, dtype=np.float64),
        intr,
        bf,
        inv_sigma2(np.asarray(problem.level), problem.scale_factor),
        problem.chi2_mono,
        problem.chi2_stereo,
        kb,
    )
    rig = rig_terms(problem, obs)
    state = BAState(np.array(problem.T_c_w, dtype=np.float64), np.array(problem.xyz_w, dtype=np.float64))
    n_obs = obs_pose.size

    def report_cost(s: BAState, keep: NDArray[np.bool_]) -> float:
        chi2, _ = observation_chi2(
            s, obs_pose[keep], obs_point[keep], obs.subset(keep), None if rig is None else rig.subset(keep)
        )
        return float(np.sum(huber_cost(chi2, obs.delta[keep]) if problem.robust else chi2))

    all_obs = np.ones(n_obs, dtype=bool)
    cost_initial = report_cost(state, all_obs) if report_costs else float("nan")
    solver = BundleSolver(_Stage(problem, obs, all_obs, problem.robust, rig), dense_max)
    out = levenberg_marquardt(
        state, solver.linearize, solver.solve, solver.retract, solver.cost, problem.iterations_first, settings, abort
    )
    state, iterations, aborted = out.x, out.iterations, out.aborted
    excluded = np.zeros(n_obs, dtype=bool)
    if not aborted and problem.iterations_second > 0:
        chi2, depth = observation_chi2(state, obs_pose, obs_point, obs, rig)
        excluded = ~((chi2 <= obs.chi2_max) & (depth > 0.0))
        if np.any(~excluded):
            stage2 = _Stage(problem, obs, ~excluded, problem.robust and robust_second_stage, rig)
            solver = BundleSolver(stage2, dense_max)
            out = levenberg_marquardt(
                state,
                solver.linearize,
                solver.solve,
                solver.retract,
                solver.cost,
                problem.iterations_second,
                settings,
                abort,
            )
            state, aborted = out.x, out.aborted
            iterations += out.iterations
    chi2, depth = observation_chi2(state, obs_pose, obs_point, obs, rig)
    outlier = excluded | ~((chi2 <= obs.chi2_max) & (depth > 0.0))
    return BundleResult(
        T_c_w=state.T_c_w,
        xyz_w=state.xyz_w,
        outlier=outlier,
        cost_initial=cost_initial,
        cost_final=report_cost(state, ~outlier) if report_costs else float("nan"),
        iterations=iterations,
        aborted=aborted,
    )
