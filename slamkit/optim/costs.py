"""Residuals and robust costs of an estimate, computed the same way whatever backend produced it.

Units: a chi2 is a squared residual whitened by the observation's information (1 / scale_factor^(2 level) for
reprojection errors), so it is dimensionless and compares with the chi-square gates (5.991 mono, 7.815 stereo).
The robust cost is g2o's Huber on chi2 (ORB-SLAM's kernel): rho(c) = c for c <= delta^2, else
2 delta sqrt(c) - delta^2, with delta^2 the problem's chi-square gate. GTSAM's Huber gives exactly half of it
(its ``graph.error``), so ``cost = 2 * graph.error()``. An observation behind its camera has chi2 = inf.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

from slamkit.geometry.sim3 import Sim3
from slamkit.problems import BundleProblem, EssentialGraphProblem, PoseOnlyProblem, Sim3Problem

__all__ = [
    "bundle_chi2",
    "bundle_cost",
    "essential_graph_cost",
    "essential_graph_residuals",
    "huber_cost",
    "kannala_brandt_project",
    "pose_chi2",
    "pose_cost",
    "sim3_chi2",
    "sim3_cost",
]

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
B = NDArray[np.bool_]


def huber_cost(chi2: F64, delta2: F64 | float) -> F64:
    """Per-residual Huber cost on chi2 (g2o's RobustKernelHuber): c if c <= delta2 else 2 sqrt(delta2 c) - delta2."""
    c = np.asarray(chi2, dtype=np.float64)
    d2 = np.broadcast_to(np.asarray(delta2, dtype=np.float64), c.shape)
    with np.errstate(invalid="ignore"):
        out: F64 = np.where(c <= d2, c, 2.0 * np.sqrt(d2 * c) - d2)
    return out


def kannala_brandt_project(pc: F64, intr: F64, k: F64) -> tuple[F64, F64]:
    """Raw fisheye pixels (u (N,), v (N,)) of camera-frame points pc (N, 3) with intrinsics intr (N, 4) and
    k1..k4 k (N, 4): the equidistant model of slamkit/problems.py (the principal point on the optical axis)."""
    r = np.hypot(pc[:, 0], pc[:, 1])
    theta = np.arctan2(r, pc[:, 2])
    t2 = theta * theta
    theta_d = theta * (1.0 + t2 * (k[:, 0] + t2 * (k[:, 1] + t2 * (k[:, 2] + t2 * k[:, 3]))))
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(r > 0.0, theta_d / np.where(r > 0.0, r, 1.0), 1.0 / pc[:, 2])
    return intr[:, 0] * s * pc[:, 0] + intr[:, 2], intr[:, 1] * s * pc[:, 1] + intr[:, 3]


def _reprojection_chi2(
    R: F64,
    t: F64,
    xyz: F64,
    uv: F64,
    u_right: F64,
    level: F64,
    intr: F64,
    bf: F64,
    scale_factor: float,
    kb: F64 | None = None,
) -> F64:
    """Per-observation chi2 of mono (u, v) or stereo (u, v, u_r) residuals; inf behind the camera.

    R: (N, 3, 3); t: (N, 3); xyz: (N, 3) world points; intr: (N, 4); bf: (N,); kb: (N, 4) k1..k4 of a
    Kannala-Brandt camera (observations in the raw fisheye image), None for the pinhole model.
    """
    pc = np.einsum("nij,nj->ni", R, xyz) + t
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_z = 1.0 / z
        if kb is None:
            u = intr[:, 0] * pc[:, 0] * inv_z + intr[:, 2]
            v = intr[:, 1] * pc[:, 1] * inv_z + intr[:, 3]
        else:
            u, v = kannala_brandt_project(pc, intr, kb)
        e2 = (uv[:, 0] - u) ** 2 + (uv[:, 1] - v) ** 2
        stereo = np.isfinite(u_right)
        ur = u - bf * inv_z
        e2 = e2 + np.where(stereo, (u_right - ur) ** 2, 0.0)
    chi2: F64 = e2 / scale_factor ** (2.0 * level)
    chi2[~(z > 0.0)] = np.inf
    return chi2


def pose_chi2(problem: PoseOnlyProblem, T_c_w: F64) -> F64:
    """(N,) chi2 of each observation of a motion-only problem at pose T_c_w (4, 4); an observation of a rig's second
    camera (``camera_index`` 1) is projected through the second camera at T_c2_c1 @ T_c_w."""
    n = len(problem.xyz_w)
    chi2 = _reprojection_chi2(
        np.broadcast_to(T_c_w[:3, :3], (n, 3, 3)),
        np.broadcast_to(T_c_w[:3, 3], (n, 3)),
        problem.xyz_w,
        problem.uv_px,
        problem.u_right_px,
        problem.level.astype(np.float64),
        np.broadcast_to(problem.intrinsics, (n, 4)),
        np.full(n, float(problem.bf)),
        problem.scale_factor,
        None if problem.distortion is None else np.broadcast_to(problem.distortion, (n, 4)),
    )
    if problem.camera_index is None or problem.T_c2_c1 is None or problem.intrinsics2 is None:
        return chi2
    second = np.asarray(problem.camera_index) == 1
    m = int(second.sum())
    if m:
        T2 = np.asarray(problem.T_c2_c1, np.float64) @ T_c_w
        chi2[second] = _reprojection_chi2(
            np.broadcast_to(T2[:3, :3], (m, 3, 3)),
            np.broadcast_to(T2[:3, 3], (m, 3)),
            problem.xyz_w[second],
            problem.uv_px[second],
            np.full(m, np.nan),
            problem.level[second].astype(np.float64),
            np.broadcast_to(problem.intrinsics2, (m, 4)),
            np.zeros(m),
            problem.scale_factor,
            None if problem.distortion2 is None else np.broadcast_to(problem.distortion2, (m, 4)),
        )
    return chi2


def _gates(u_right: F64, chi2_mono: float, chi2_stereo: float) -> F64:
    out: F64 = np.where(np.isfinite(u_right), chi2_stereo, chi2_mono)
    return out


def pose_cost(problem: PoseOnlyProblem, T_c_w: F64, active: B | None = None) -> float:
    """Huber cost of the (active) observations of a motion-only problem at T_c_w."""
    chi2 = pose_chi2(problem, T_c_w)
    rho = huber_cost(chi2, _gates(problem.u_right_px, problem.chi2_mono, problem.chi2_stereo))
    return float(rho.sum() if active is None else rho[active].sum())


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _pinhole_bundle_chi2(
    R: F64, t: F64, xyz: F64, obs_pose: I64, obs_point: I64, uv: F64, u_right: F64, den: F64, intr: F64, bf: F64
) -> F64:  # pragma: no cover - compiled
    """:func:`_reprojection_chi2` of a one-camera pinhole bundle problem without its per-observation gathers: R (K, 3,
    3), t (K, 3), intr (K, 4), bf (K,) per pose, xyz (M, 3) per point, den (E,) = scale_factor^(2 level). The same
    operations in the same order, numpy's einsum summing a 3-term product as (p0 + p2) + p1 (so the same bits)."""
    E = obs_pose.shape[0]
    chi2 = np.empty(E)
    for e in range(E):
        k = obs_pose[e]
        j = obs_point[e]
        x = (R[k, 0, 0] * xyz[j, 0] + R[k, 0, 2] * xyz[j, 2]) + R[k, 0, 1] * xyz[j, 1] + t[k, 0]
        y = (R[k, 1, 0] * xyz[j, 0] + R[k, 1, 2] * xyz[j, 2]) + R[k, 1, 1] * xyz[j, 1] + t[k, 1]
        z = (R[k, 2, 0] * xyz[j, 0] + R[k, 2, 2] * xyz[j, 2]) + R[k, 2, 1] * xyz[j, 1] + t[k, 2]
        if not z > 0.0:
            chi2[e] = np.inf
            continue
        inv_z = 1.0 / z
        u = intr[k, 0] * x * inv_z + intr[k, 2]
        v = intr[k, 1] * y * inv_z + intr[k, 3]
        du = uv[e, 0] - u
        dv = uv[e, 1] - v
        e2 = du * du + dv * dv
        if np.isfinite(u_right[e]):
            dr = u_right[e] - (u - bf[k] * inv_z)
            e2 = e2 + dr * dr
        else:
            e2 = e2 + 0.0
        chi2[e] = e2 / den[e]
    return chi2


def bundle_chi2(problem: BundleProblem, T_c_w: F64, xyz_w: F64) -> F64:
    """(E,) chi2 of each observation at poses T_c_w (K, 4, 4) and points xyz_w (M, 3); an observation of a rig's
    second camera (``camera_index`` 1) through the second camera at T_c2_c1[k] @ T_c_w[k]."""
    if problem.distortion is None and problem.camera_index is None:  # one pinhole camera: one compiled pass
        T_k = np.asarray(T_c_w, np.float64)
        return np.asarray(
            _pinhole_bundle_chi2(
                np.ascontiguousarray(T_k[:, :3, :3]),
                np.ascontiguousarray(T_k[:, :3, 3]),
                np.ascontiguousarray(xyz_w, np.float64),
                np.asarray(problem.obs_pose, np.int64),
                np.asarray(problem.obs_point, np.int64),
                np.ascontiguousarray(problem.uv_px, np.float64),
                np.ascontiguousarray(problem.u_right_px, np.float64),
                problem.scale_factor ** (2.0 * problem.level.astype(np.float64)),
                np.ascontiguousarray(problem.intrinsics, np.float64),
                np.ascontiguousarray(problem.bf, np.float64),
            )
        )
    T = T_c_w[problem.obs_pose]
    chi2 = _reprojection_chi2(
        T[:, :3, :3],
        T[:, :3, 3],
        xyz_w[problem.obs_point],
        problem.uv_px,
        problem.u_right_px,
        problem.level.astype(np.float64),
        problem.intrinsics[problem.obs_pose],
        problem.bf[problem.obs_pose],
        problem.scale_factor,
        None if problem.distortion is None else np.asarray(problem.distortion)[problem.obs_pose],
    )
    if problem.camera_index is None or problem.T_c2_c1 is None or problem.intrinsics2 is None:
        return chi2
    second = np.flatnonzero(np.asarray(problem.camera_index) == 1)
    if second.size:
        k = problem.obs_pose[second]
        T2 = np.asarray(problem.T_c2_c1, np.float64)[k] @ T_c_w[k]
        chi2[second] = _reprojection_chi2(
            T2[:, :3, :3],
            T2[:, :3, 3],
            xyz_w[problem.obs_point[second]],
            problem.uv_px[second],
            np.full(second.size, np.nan),
            problem.level[second].astype(np.float64),
            np.asarray(problem.intrinsics2, np.float64)[k],
            np.zeros(second.size),
            problem.scale_factor,
            None if problem.distortion2 is None else np.asarray(problem.distortion2, np.float64)[k],
        )
    return chi2


def bundle_cost(problem: BundleProblem, T_c_w: F64, xyz_w: F64, active: B | None = None) -> float:
    """Robust (Huber, or plain when ``problem.robust`` is False) cost of the active observations."""
    chi2 = bundle_chi2(problem, T_c_w, xyz_w)
    rho = (
        huber_cost(chi2, _gates(problem.u_right_px, problem.chi2_mono, problem.chi2_stereo)) if problem.robust else chi2
    )
    return float(rho.sum() if active is None else rho[active].sum())


def sim3_chi2(problem: Sim3Problem, S_12: F64) -> tuple[F64, F64]:
    """(N,) chi2 of direction 1 (uv1 vs project_1(S_12 xyz2_c2)) and (N,) of direction 2 (uv2 vs project_2(S_21 xyz1_c1)),
    each through its keyframe's camera model (``distortion1`` / ``distortion2``: Kannala-Brandt when given)."""
    n = len(problem.xyz1_c1)

    def direction(S: F64, xyz: F64, uv: F64, level: I64, intrinsics: F64, distortion: F64 | None) -> F64:
        return _reprojection_chi2(
            np.broadcast_to(S[:3, :3], (n, 3, 3)),
            np.broadcast_to(S[:3, 3], (n, 3)),
            xyz,
            uv,
            np.full(n, np.nan),
            level.astype(np.float64),
            np.broadcast_to(intrinsics, (n, 4)),
            np.zeros(n),
            problem.scale_factor,
            None if distortion is None else np.broadcast_to(distortion, (n, 4)),
        )

    e1 = direction(S_12, problem.xyz2_c2, problem.uv1_px, problem.level1, problem.intrinsics1, problem.distortion1)
    e2 = direction(
        np.asarray(np.linalg.inv(S_12), np.float64),
        problem.xyz1_c1,
        problem.uv2_px,
        problem.level2,
        problem.intrinsics2,
        problem.distortion2,
    )
    return e1, e2


def sim3_cost(problem: Sim3Problem, S_12: F64, active: B | None = None) -> float:
    """Huber cost (delta^2 = problem.chi2 per direction) of the active matches, both directions summed."""
    e1, e2 = sim3_chi2(problem, S_12)
    rho = huber_cost(e1, problem.chi2) + huber_cost(e2, problem.chi2)
    return float(rho.sum() if active is None else rho[active].sum())


def essential_graph_residuals(problem: EssentialGraphProblem, S_c_w: F64) -> F64:
    """(E, 7) residuals log_Sim3(S_ij S_jw S_iw^-1) = [omega, v, lambda] of each edge at poses S_c_w (K, 4, 4)."""
    S_iw_inv = np.linalg.inv(S_c_w[problem.edge_i])
    M = problem.S_ij @ S_c_w[problem.edge_j] @ S_iw_inv
    return np.stack([Sim3.from_matrix(m).log() for m in M])


def essential_graph_cost(problem: EssentialGraphProblem, S_c_w: F64) -> float:
    """Sum over edges of weight * |residual|^2 (identity information; the lambda term is 0 in the SE3 variant)."""
    r = essential_graph_residuals(problem, S_c_w)
    w = np.ones(len(r)) if problem.weights is None else problem.weights
    return float((w * (r**2).sum(axis=1)).sum())
