"""numba kernels of bundle adjustment with a two-camera rig (non-rectified stereo, ORB-SLAM3 EdgeSE3ProjectXYZToBody).

Used only for problems with second-camera observations (``BundleProblem.camera_index``); one-camera problems keep
slamkit_scipy.kernels. Each observation e carries an extrinsic (Rx[e], tx[e]) from its keyframe's body camera to the
camera that saw it (the identity for camera 1, T_c2_c1 for camera 2), its own model (cam[e] = fx, fy, cx, cy, k1..k4
of the observing camera; ``fish[e]``: Kannala-Brandt, else the pinhole; ``intr`` is not read) and, for camera-1 pinhole observations only, a right
coordinate. With p1 = R_k X + t_k (body camera) and p = Rx p1 + tx (observing camera) the residual is the projection
of p minus the observation; with A = d r / d p, A' = A Rx: d r / d xi = (cross(p1, A'_row), A'_row) for the body
pose's left perturbation and d r / d X = A' R_k. The blocks have the layout of ``kernels.ba_linearize`` (W transposed
in 8-lane rows), so the Schur complement and back-substitution kernels are shared.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

from slamkit.optim.kannala_brandt import kb_jacobian, kb_project
from slamkit_scipy.kernels import _accumulate_block

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
B = NDArray[np.bool_]


@numba.njit(cache=True, nogil=True, inline="always")
def _points(
    R: F64, t: F64, X: F64, Rx: F64, tx: F64, k: int, j: int, e: int, p1: F64, p: F64
) -> None:  # pragma: no cover - compiled
    """p1 (3,) = R_k X_j + t_k (body camera), p (3,) = Rx_e p1 + tx_e (observing camera)."""
    for a in range(3):
        p1[a] = R[k, a, 0] * X[j, 0] + R[k, a, 1] * X[j, 1] + R[k, a, 2] * X[j, 2] + t[k, a]
    for a in range(3):
        p[a] = Rx[e, a, 0] * p1[0] + Rx[e, a, 1] * p1[1] + Rx[e, a, 2] * p1[2] + tx[e, a]


@numba.njit(cache=True, nogil=True, inline="always")
def _residual(
    p: F64, e: int, uvr: F64, stereo: B, intr: F64, bf: F64, cam: F64, fish: B, r: F64
) -> int:  # pragma: no cover - compiled
    """r (3,) residual rows of observation e at its camera point p -> number of rows (2 or 3)."""
    iz = 1.0 / p[2]
    if fish[e]:
        u, v = kb_project(p[0], p[1], p[2], cam[e])
    else:
        u = cam[e, 0] * p[0] * iz + cam[e, 2]
        v = cam[e, 1] * p[1] * iz + cam[e, 3]
    r[0] = u - uvr[e, 0]
    r[1] = v - uvr[e, 1]
    if stereo[e]:
        r[2] = u - bf[e] * iz - uvr[e, 2]
        return 3
    r[2] = 0.0
    return 2


@numba.njit(cache=True, nogil=True)
def rig_chi2(
    R: F64,
    t: F64,
    X: F64,
    obs_pose: I64,
    obs_point: I64,
    uvr: F64,
    stereo: B,
    intr: F64,
    bf: F64,
    info: F64,
    cam: F64,
    fish: B,
    Rx: F64,
    tx: F64,
) -> tuple[F64, F64]:  # pragma: no cover - compiled
    """-> chi2 (E,) and depth (E,) m of every observation in the camera that saw it."""
    E = obs_pose.shape[0]
    chi2 = np.empty(E)
    depth = np.empty(E)
    p1 = np.zeros(3)
    p = np.zeros(3)
    r = np.zeros(3)
    for e in range(E):
        _points(R, t, X, Rx, tx, obs_pose[e], obs_point[e], e, p1, p)
        rows = _residual(p, e, uvr, stereo, intr, bf, cam, fish, r)
        s = 0.0
        for a in range(rows):
            s += r[a] * r[a]
        chi2[e] = info[e] * s
        depth[e] = p[2]
    return chi2, depth


@numba.njit(cache=True, nogil=True)
def rig_cost(
    R: F64,
    t: F64,
    X: F64,
    obs_pose: I64,
    obs_point: I64,
    uvr: F64,
    stereo: B,
    intr: F64,
    bf: F64,
    info: F64,
    delta: F64,
    robust: bool,
    cam: F64,
    fish: B,
    Rx: F64,
    tx: F64,
) -> float:  # pragma: no cover - compiled
    """Sum of rho(chi2) (Huber when ``robust``) over the observations."""
    chi2, _ = rig_chi2(R, t, X, obs_pose, obs_point, uvr, stereo, intr, bf, info, cam, fish, Rx, tx)
    cost = 0.0
    for e in range(chi2.shape[0]):
        d = delta[e]
        if robust and chi2[e] > d * d:
            cost += 2.0 * d * np.sqrt(chi2[e]) - d * d
        else:
            cost += chi2[e]
    return cost


@numba.njit(cache=True, nogil=True)
def rig_linearize(
    R: F64,
    t: F64,
    X: F64,
    obs_pose: I64,
    obs_point: I64,
    c: I64,
    p_idx: I64,
    uvr: F64,
    stereo: B,
    intr: F64,
    bf: F64,
    info: F64,
    delta: F64,
    robust: bool,
    nc: int,
    npt: int,
    cam: F64,
    fish: B,
    Rx: F64,
    tx: F64,
) -> tuple[F64, F64, F64, F64, F64, float]:  # pragma: no cover - compiled
    """-> U (nc, 6, 6), V (npt, 3, 3), WT (E, 3, 8), gc (nc, 6), gp (npt, 3), robust cost: kernels.ba_linearize's
    blocks, in its layout (each W transposed in 8-lane rows, lanes 6 and 7 zero), for observations of either camera of
    a rig (module docstring)."""
    E = obs_pose.shape[0]
    U = np.zeros((nc, 6, 6))
    V = np.zeros((npt, 3, 3))
    WT = np.zeros((E, 3, 8))
    gc = np.zeros((nc, 6))
    gp = np.zeros((npt, 3))
    cost = 0.0
    A = np.zeros((3, 3))
    Ab = np.zeros((3, 3))
    Jc = np.zeros((3, 6))
    Jp = np.zeros((3, 3))
    r = np.zeros(3)
    p1 = np.zeros(3)
    pc = np.zeros(3)
    for e in range(E):
        k = obs_pose[e]
        j = obs_point[e]
        _points(R, t, X, Rx, tx, k, j, e, p1, pc)
        rows = _residual(pc, e, uvr, stereo, intr, bf, cam, fish, r)
        chi2 = 0.0
        for a in range(rows):
            chi2 += r[a] * r[a]
        chi2 *= info[e]
        d = delta[e]
        if robust and chi2 > d * d:
            cost += 2.0 * d * np.sqrt(chi2) - d * d
            w = info[e] * d / np.sqrt(chi2)
        else:
            cost += chi2
            w = info[e]
        x, y, z = pc[0], pc[1], pc[2]
        if fish[e]:
            kb_jacobian(x, y, z, cam[e], A)
        else:
            fx = cam[e, 0]
            fy = cam[e, 1]
            iz = 1.0 / z
            iz2 = iz * iz
            A[0, 0] = fx * iz
            A[0, 1] = 0.0
            A[0, 2] = -fx * x * iz2
            A[1, 0] = 0.0
            A[1, 1] = fy * iz
            A[1, 2] = -fy * y * iz2
            A[2, 0] = fx * iz
            A[2, 1] = 0.0
            A[2, 2] = (bf[e] - fx * x) * iz2
        # A' = A Rx: the Jacobian with respect to the body camera's point p1
        for a in range(rows):
            for b in range(3):
                Ab[a, b] = A[a, 0] * Rx[e, 0, b] + A[a, 1] * Rx[e, 1, b] + A[a, 2] * Rx[e, 2, b]
        x1, y1, z1 = p1[0], p1[1], p1[2]
        for a in range(rows):
            Jc[a, 0] = y1 * Ab[a, 2] - z1 * Ab[a, 1]
            Jc[a, 1] = z1 * Ab[a, 0] - x1 * Ab[a, 2]
            Jc[a, 2] = x1 * Ab[a, 1] - y1 * Ab[a, 0]
            Jc[a, 3] = Ab[a, 0]
            Jc[a, 4] = Ab[a, 1]
            Jc[a, 5] = Ab[a, 2]
            for b in range(3):
                Jp[a, b] = Ab[a, 0] * R[k, 0, b] + Ab[a, 1] * R[k, 1, b] + Ab[a, 2] * R[k, 2, b]
        ci = c[e]
        pi = p_idx[e]
        if ci >= 0:
            _accumulate_block(Jc, r, rows, w, gc[ci], U[ci])
        if pi >= 0:
            _accumulate_block(Jp, r, rows, w, gp[pi], V[pi])
        if ci >= 0 and pi >= 0:
            for i in range(6):
                for jj in range(3):
                    s = 0.0
                    for a in range(rows):
                        s += Jc[a, i] * Jp[a, jj]
                    WT[e, jj, i] = w * s
    for q in range(nc):
        for i in range(6):
            for jj in range(i):
                U[q, i, jj] = U[q, jj, i]
    for q in range(npt):
        for i in range(3):
            for jj in range(i):
                V[q, i, jj] = V[q, jj, i]
    return U, V, WT, gc, gp, cost
