"""Motion-only bundle adjustment for tracking (ORB-SLAM ``Optimizer::PoseOptimization``), compiled with numba.

Tracking optimises one pose against a few hundred fixed points up to three times a frame; a general
optimizer call (problem validation, vectorised NumPy over (E, 3, 6) Jacobians, a Python LM loop) costs
several milliseconds there, most of it interpreter overhead. This module runs the same algorithm in one
numba kernel that releases the GIL, so local mapping can run beside tracking:

- ``rounds`` (4) optimisations of ``iterations_per_round`` (10) Levenberg-Marquardt iterations, each round
  starting again from the initial pose (ORB-SLAM resets the vertex's estimate) and using only the
  observations classified as inliers;
- the Huber kernel (delta = sqrt(chi2 gate)) in the first two rounds, none from the third on;
- after every round every observation is re-classified with the chi-square gate (5.991 for monocular ones),
  a point behind the camera being an outlier whatever its chi2; an outlier may come back in a later round.

The LM step is g2o's (and slamkit_scipy.lm's): initial damping tau * max diag(H), Nielsen's update, up to ten
damped solves per iteration until one lowers the cost. Residual r = projection - observation (px), information
1 / scale_factor^(2 level), left perturbation T <- exp(xi) T with xi = [omega, v]
(slamkit.geometry.se3_kernels.se3_exp_times, shared with the scipy backend's bundle adjustment).
``optimize_pose`` takes and returns the optimizer interface's PoseOnlyProblem / PoseOnlyResult, so it can stand
in for ``Optimizer.optimize_pose``. Camera models: the pinhole of the undistorted image and Kannala-Brandt (raw
fisheye pixels, ``problem.distortion`` = k1..k4). Stereo/RGB-D observations (finite ``u_right_px``, pinhole only)
add the right-coordinate residual u - bf / z - u_right (3 dof, chi-square gate ``chi2_stereo`` = 7.815; ORB-SLAM2
EdgeStereoSE3ProjectXYZOnlyPose) with the same information 1 / scale_factor^(2 level).
A two-camera rig (non-rectified stereo, ORB-SLAM3 EdgeSE3ProjectXYZOnlyPoseToBody): an observation of the second
camera (``problem.camera_index`` 1) is projected through its own model at T_2 = T_c2_c1 T (fixed extrinsic); its
Jacobian is the second camera's own left-perturbation Jacobian times the adjoint of T_c2_c1, since
T_c2_c1 exp(xi) T = exp(Ad(T_c2_c1) xi) T_c2_c1 T. Its depth check is in the second camera.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

from slamkit.geometry.se3_kernels import se3_exp_times
from slamkit.optim.kannala_brandt import kb_jacobian, kb_project
from slamkit.problems import CAMERA_KANNALA_BRANDT, CAMERA_PINHOLE, PoseOnlyProblem, PoseOnlyResult

F64 = NDArray[np.float64]

#: g2o's LM: initial damping = tau * max diag(H); damped solves per iteration; relative cost tolerance.
LM_TAU = 1e-5
LM_MAX_TRIALS = 10
LM_REL_TOL = 1e-10


@numba.njit(cache=True, nogil=True, inline="always")
def _residual(
    T: F64, X: F64, uv: F64, cam: F64, fisheye: bool, i: int
) -> tuple[float, float, float, float, float]:  # pragma: no cover - numba
    """Camera point (x, y, z) of point i at pose T and its residual (ru, rv), px. cam: (8,) fx, fy, cx, cy and
    k1..k4 of the Kannala-Brandt model when ``fisheye`` (else the pinhole model of the undistorted image)."""
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    x = T[0, 0] * X[i, 0] + T[0, 1] * X[i, 1] + T[0, 2] * X[i, 2] + T[0, 3]
    y = T[1, 0] * X[i, 0] + T[1, 1] * X[i, 1] + T[1, 2] * X[i, 2] + T[1, 3]
    z = T[2, 0] * X[i, 0] + T[2, 1] * X[i, 1] + T[2, 2] * X[i, 2] + T[2, 3]
    if fisheye:
        u, v = kb_project(x, y, z, cam)
        return x, y, z, u - uv[i, 0], v - uv[i, 1]
    iz = 1.0 / z
    return x, y, z, fx * x * iz + cx - uv[i, 0], fy * y * iz + cy - uv[i, 1]


@numba.njit(cache=True, nogil=True, inline="always")
def _rho(chi2: float, delta: float, robust: bool) -> float:  # pragma: no cover - numba
    """Huber cost of a chi2 value (g2o's RobustKernelHuber), or chi2 itself."""
    if not robust or chi2 <= delta * delta:
        return chi2
    return 2.0 * delta * np.sqrt(chi2) - delta * delta


@numba.njit(cache=True, nogil=True, inline="always")
def _right_residual(x: float, z: float, cam: F64, ur: F64, bf: float, i: int) -> float:  # pragma: no cover - numba
    """Residual of the right coordinate of stereo/RGB-D observation i at camera point (x, ., z) (ORB-SLAM
    EdgeStereoSE3ProjectXYZOnlyPose): u_r = fx x / z + cx - bf / z, minus the observed u_right, px (pinhole only)."""
    iz = 1.0 / z
    return cam[0] * x * iz + cam[2] - bf * iz - ur[i]


@numba.njit(cache=True, nogil=True)
def _cost(
    T: F64,
    X: F64,
    uv: F64,
    info: F64,
    delta: F64,
    use: NDArray[np.bool_],
    cam: F64,
    fisheye: bool,
    robust: bool,
    stereo: NDArray[np.bool_],
    ur: F64,
    bf: float,
    which: NDArray[np.int64],
    T21: F64,
    cam2: F64,
    fisheye2: bool,
) -> float:  # pragma: no cover - numba
    f = 0.0
    T2 = T21 @ T
    for i in range(X.shape[0]):
        if use[i]:
            if which[i] == 1:
                x, _, z, ru, rv = _residual(T2, X, uv, cam2, fisheye2, i)
            else:
                x, _, z, ru, rv = _residual(T, X, uv, cam, fisheye, i)
            e2 = ru * ru + rv * rv
            if stereo[i]:
                rr = _right_residual(x, z, cam, ur, bf, i)
                e2 += rr * rr
            f += _rho(info[i] * e2, delta[i], robust)
    return f


@numba.njit(cache=True, nogil=True, inline="always")
def _kb_jacobian_rows(x: float, y: float, z: float, cam: F64, J: F64) -> None:  # pragma: no cover - numba
    """J (2, 6) = d r / d xi of a Kannala-Brandt observation: rows A = d uv / d p_c, d r / d omega = cross(p_c, A_row),
    d r / d v = A_row."""
    A = np.empty((2, 3))
    kb_jacobian(x, y, z, cam, A)
    for row in range(2):
        J[row, 0] = y * A[row, 2] - z * A[row, 1]
        J[row, 1] = z * A[row, 0] - x * A[row, 2]
        J[row, 2] = x * A[row, 1] - y * A[row, 0]
        J[row, 3], J[row, 4], J[row, 5] = A[row, 0], A[row, 1], A[row, 2]


@numba.njit(cache=True, nogil=True)
def _second_camera_rows(
    x: float, y: float, z: float, cam2: F64, fisheye2: bool, Ad21: F64, J: F64
) -> None:  # pragma: no cover - numba
    """J (2, 6) = d r / d xi of a second-camera observation at its camera point (x, y, z): the second camera's own
    left-perturbation rows (cross(p_2, a), a) times Ad(T_c2_c1) (6, 6)."""
    J2 = np.zeros((2, 6))
    if fisheye2:
        _kb_jacobian_rows(x, y, z, cam2, J2)
    else:
        fx, fy = cam2[0], cam2[1]
        iz = 1.0 / z
        iz2 = iz * iz
        a00, a02 = fx * iz, -fx * x * iz2
        a11, a12 = fy * iz, -fy * y * iz2
        J2[0, 0], J2[0, 1], J2[0, 2] = y * a02, z * a00 - x * a02, -y * a00
        J2[0, 3], J2[0, 4], J2[0, 5] = a00, 0.0, a02
        J2[1, 0], J2[1, 1], J2[1, 2] = y * a12 - z * a11, -x * a12, x * a11
        J2[1, 3], J2[1, 4], J2[1, 5] = 0.0, a11, a12
    for r in range(2):
        for a in range(6):
            s = 0.0
            for b in range(6):
                s += J2[r, b] * Ad21[b, a]
            J[r, a] = s


@numba.njit(cache=True, nogil=True)
def _linearize(
    T: F64,
    X: F64,
    uv: F64,
    info: F64,
    delta: F64,
    use: NDArray[np.bool_],
    cam: F64,
    fisheye: bool,
    robust: bool,
    stereo: NDArray[np.bool_],
    ur: F64,
    bf: float,
    which: NDArray[np.int64],
    T21: F64,
    cam2: F64,
    fisheye2: bool,
    Ad21: F64,
) -> tuple[F64, F64, float]:  # pragma: no cover - numba
    """H = sum J^T w J (6, 6), g = sum J^T w r (6,), robust cost; w = info * rho'(chi2) (IRLS). A stereo
    observation (``stereo[i]``) adds the right-coordinate row (u_r = fx x / z + cx - bf / z) with the same
    information (ORB-SLAM: Info = I_3 / sigma2)."""
    fx, fy = cam[0], cam[1]
    H = np.zeros((6, 6))
    g = np.zeros(6)
    J = np.zeros((2, 6))
    f = 0.0
    T2 = T21 @ T
    for i in range(X.shape[0]):
        if not use[i]:
            continue
        if which[i] == 1:
            x, y, z, ru, rv = _residual(T2, X, uv, cam2, fisheye2, i)
        else:
            x, y, z, ru, rv = _residual(T, X, uv, cam, fisheye, i)
        rr = 0.0
        if stereo[i]:
            rr = _right_residual(x, z, cam, ur, bf, i)
            chi2 = info[i] * (ru * ru + rv * rv + rr * rr)
        else:
            chi2 = info[i] * (ru * ru + rv * rv)
        w = info[i]
        if robust and chi2 > delta[i] * delta[i]:
            w *= delta[i] / np.sqrt(max(chi2, 1e-300))
        f += _rho(chi2, delta[i], robust)
        if which[i] == 1:
            _second_camera_rows(x, y, z, cam2, fisheye2, Ad21, J)
        elif fisheye:
            _kb_jacobian_rows(x, y, z, cam, J)
        else:
            iz = 1.0 / z
            iz2 = iz * iz
            # d r / d p_c rows a0 = (fx/z, 0, -fx x/z^2), a1 = (0, fy/z, -fy y/z^2); d r / d omega = cross(p_c, a)
            a00, a02 = fx * iz, -fx * x * iz2
            a11, a12 = fy * iz, -fy * y * iz2
            J[0, 0], J[0, 1], J[0, 2] = y * a02, z * a00 - x * a02, -y * a00
            J[0, 3], J[0, 4], J[0, 5] = a00, 0.0, a02
            J[1, 0], J[1, 1], J[1, 2] = y * a12 - z * a11, -x * a12, x * a11
            J[1, 3], J[1, 4], J[1, 5] = 0.0, a11, a12
        for a in range(6):
            ga = w * (J[0, a] * ru + J[1, a] * rv)
            g[a] += ga
            for b in range(a, 6):
                H[a, b] += w * (J[0, a] * J[0, b] + J[1, a] * J[1, b])
        if stereo[i]:
            # d u_r / d p_c = (fx/z, 0, -fx x/z^2 + bf/z^2) (ORB-SLAM EdgeStereoSE3ProjectXYZOnlyPose::linearizeOplus)
            iz = 1.0 / z
            a20, a22 = fx * iz, -fx * x * iz * iz + bf * iz * iz
            Jr = (y * a22, z * a20 - x * a22, -y * a20, a20, 0.0, a22)
            for a in range(6):
                g[a] += w * Jr[a] * rr
                for b in range(a, 6):
                    H[a, b] += w * Jr[a] * Jr[b]
    for a in range(6):
        for b in range(a):
            H[a, b] = H[b, a]
    return H, g, f


@numba.njit(cache=True, nogil=True)
def _solve_damped(H: F64, g: F64, lam: float) -> F64:  # pragma: no cover - numba
    """h with (H + lam I) h = -g by Cholesky; NaNs when the damped matrix is not positive definite."""
    L = np.zeros((6, 6))
    for i in range(6):
        for j in range(i + 1):
            s = H[i, j] + (lam if i == j else 0.0)
            for k in range(j):
                s -= L[i, k] * L[j, k]
            if i == j:
                if not s > 0.0:
                    return np.full(6, np.nan)
                L[i, i] = np.sqrt(s)
            else:
                L[i, j] = s / L[j, j]
    y = np.zeros(6)
    for i in range(6):
        s = -g[i]
        for k in range(i):
            s -= L[i, k] * y[k]
        y[i] = s / L[i, i]
    h = np.zeros(6)
    for i in range(5, -1, -1):
        s = y[i]
        for k in range(i + 1, 6):
            s -= L[k, i] * h[k]
        h[i] = s / L[i, i]
    return h


@numba.njit(cache=True, nogil=True)
def _levenberg_marquardt(
    T: F64,
    X: F64,
    uv: F64,
    info: F64,
    delta: F64,
    use: NDArray[np.bool_],
    cam: F64,
    fisheye: bool,
    robust: bool,
    stereo: NDArray[np.bool_],
    ur: F64,
    bf: float,
    which: NDArray[np.int64],
    T21: F64,
    cam2: F64,
    fisheye2: bool,
    Ad21: F64,
    iterations: int,
    tau: float,
    max_trials: int,
    rel_tol: float,
) -> tuple[F64, int]:  # pragma: no cover - numba
    """Up to ``iterations`` LM iterations from T (the driver of slamkit_scipy.lm, specialised to one pose)."""
    lam = -1.0
    nu = 2.0
    done = 0
    stale = True
    H = np.zeros((6, 6))
    g = np.zeros(6)
    f = 0.0
    for _ in range(iterations):
        if stale:
            H, g, f = _linearize(
                T, X, uv, info, delta, use, cam, fisheye, robust, stereo, ur, bf, which, T21, cam2, fisheye2, Ad21
            )
            stale = False
        if lam < 0.0:
            hmax = 0.0
            for a in range(6):
                hmax = max(hmax, H[a, a])
            lam = tau * max(hmax, 1e-12)
        accepted = False
        decrease = 0.0
        for _trial in range(max_trials):
            h = _solve_damped(H, g, lam)
            if not np.all(np.isfinite(h)):
                lam *= nu
                nu *= 2.0
                continue
            predicted = 0.0
            for a in range(6):
                predicted += h[a] * (lam * h[a] - g[a])
            if predicted <= rel_tol * f:
                break  # the model promises less than the tolerance: converged
            T_new = se3_exp_times(h, T)
            f_new = _cost(
                T_new, X, uv, info, delta, use, cam, fisheye, robust, stereo, ur, bf, which, T21, cam2, fisheye2
            )
            rho = (f - f_new) / predicted if predicted > 0.0 else -1.0
            if rho > 0.0 and np.isfinite(f_new):
                lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                nu = 2.0
                accepted = True
                decrease = f - f_new
                T, f = T_new, f_new
                stale = True
                break
            lam *= nu
            nu *= 2.0
        done += 1
        if not accepted or decrease <= rel_tol * max(f, 1e-300):
            break
    return T, done


@numba.njit(cache=True, nogil=True)
def _optimize_pose_kernel(
    T0: F64,
    X: F64,
    uv: F64,
    info: F64,
    chi2_max: F64,
    cam: F64,
    fisheye: bool,
    stereo: NDArray[np.bool_],
    ur: F64,
    bf: float,
    which: NDArray[np.int64],
    T21: F64,
    cam2: F64,
    fisheye2: bool,
    Ad21: F64,
    rounds: int,
    iterations: int,
    tau: float,
    max_trials: int,
    rel_tol: float,
) -> tuple[F64, NDArray[np.bool_], int, float, float]:  # pragma: no cover - numba
    n = X.shape[0]
    delta = np.sqrt(chi2_max)
    inlier = np.ones(n, np.bool_)
    cost_initial = _cost(T0, X, uv, info, delta, inlier, cam, fisheye, True, stereo, ur, bf, which, T21, cam2, fisheye2)
    T = T0.copy()
    total = 0
    for it in range(rounds):
        T, done = _levenberg_marquardt(
            T0.copy(),
            X,
            uv,
            info,
            delta,
            inlier,
            cam,
            fisheye,
            it < 2,
            stereo,
            ur,
            bf,
            which,
            T21,
            cam2,
            fisheye2,
            Ad21,
            iterations,
            tau,
            max_trials,
            rel_tol,
        )
        total += done
        any_in = False
        T2 = T21 @ T
        for i in range(n):
            if which[i] == 1:
                x, _, z, ru, rv = _residual(T2, X, uv, cam2, fisheye2, i)
            else:
                x, _, z, ru, rv = _residual(T, X, uv, cam, fisheye, i)
            if stereo[i]:
                rr = _right_residual(x, z, cam, ur, bf, i)
                inlier[i] = (info[i] * (ru * ru + rv * rv + rr * rr) <= chi2_max[i]) and z > 0.0
            else:
                inlier[i] = (info[i] * (ru * ru + rv * rv) <= chi2_max[i]) and z > 0.0
            any_in = any_in or inlier[i]
        if not any_in:
            break
    cost_final = _cost(T, X, uv, info, delta, inlier, cam, fisheye, True, stereo, ur, bf, which, T21, cam2, fisheye2)
    return T, inlier, total, cost_initial, cost_final


def _adjoint(T: F64) -> F64:
    """(6, 6) Ad(T) for twists xi = [omega, v]: T exp(xi) = exp(Ad(T) xi) T, Ad = [[R, 0], [hat(t) R, R]]."""
    R, t = T[:3, :3], T[:3, 3]
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    Ad = np.zeros((6, 6))
    Ad[:3, :3] = R
    Ad[3:, 3:] = R
    Ad[3:, :3] = tx @ R
    return Ad


def _second_camera(
    problem: PoseOnlyProblem, n: int, cam: F64, fisheye: bool
) -> tuple[NDArray[np.int64], F64, F64, bool]:
    """(which (N,) int64, T_c2_c1 (4, 4), cam2 (8,), fisheye2) of a two-camera problem; for a one-camera problem all
    zeros, the identity and the first camera (the kernel never reads them then)."""
    if problem.camera_index is None:
        return np.zeros(n, np.int64), np.eye(4), cam, fisheye
    which = np.ascontiguousarray(problem.camera_index, np.int64).reshape(-1)
    if which.shape != (n,) or not np.isin(which, (0, 1)).all():
        raise ValueError(f"pose problem: camera_index must be (N,) = ({n},) of 0 / 1; got {which.shape}")
    if not (which == 1).any():
        return which, np.eye(4), cam, fisheye
    if problem.T_c2_c1 is None or problem.intrinsics2 is None:
        raise ValueError("pose problem: second-camera observations need T_c2_c1 and intrinsics2")
    if np.isfinite(np.asarray(problem.u_right_px)[which == 1]).any():
        raise ValueError("pose problem: a second-camera observation has a right coordinate; expected NaN")
    fisheye2 = problem.camera_model2 == CAMERA_KANNALA_BRANDT
    if problem.camera_model2 not in (CAMERA_PINHOLE, CAMERA_KANNALA_BRANDT):
        raise ValueError(f"pose problem: camera_model2 {problem.camera_model2!r} is not supported here")
    cam2 = np.zeros(8)
    cam2[:4] = np.asarray(problem.intrinsics2, np.float64)
    if fisheye2:
        if problem.distortion2 is None or np.shape(problem.distortion2) != (4,):
            raise ValueError("pose problem: a kannala_brandt second camera needs distortion2 k1..k4 of shape (4,)")
        cam2[4:] = np.asarray(problem.distortion2, np.float64)
    T21 = np.ascontiguousarray(problem.T_c2_c1, np.float64)
    if T21.shape != (4, 4) or not np.all(np.isfinite(T21)):
        raise ValueError("pose problem: T_c2_c1 must be a finite (4, 4) transform")
    return which, T21, cam2, fisheye2


def optimize_pose(problem: PoseOnlyProblem) -> PoseOnlyResult:
    """Motion-only BA of a PoseOnlyProblem, monocular and stereo/RGB-D observations (see the module docstring).

    Raises ValueError on mismatched shapes, non-finite inputs, or stereo observations without a pinhole camera and
    bf > 0.
    """
    X = np.ascontiguousarray(problem.xyz_w, np.float64)
    uv = np.ascontiguousarray(problem.uv_px, np.float64)
    n = X.shape[0]
    T0 = np.ascontiguousarray(problem.T_c_w_init, np.float64)
    level = np.asarray(problem.level)
    if X.shape != (n, 3) or uv.shape != (n, 2) or level.shape != (n,) or T0.shape != (4, 4):
        raise ValueError(
            f"pose problem: expected xyz_w (N, 3), uv_px (N, 2), level (N,), T_c_w_init (4, 4); got "
            f"{X.shape}, {uv.shape}, {level.shape}, {T0.shape}"
        )
    ur = np.ascontiguousarray(problem.u_right_px, np.float64).reshape(-1)
    if ur.shape != (n,):
        raise ValueError(f"pose problem: expected u_right_px (N,) = ({n},); got {ur.shape}")
    stereo = np.isfinite(ur)
    bf = float(problem.bf)
    if stereo.any() and (problem.camera_model != CAMERA_PINHOLE or not bf > 0.0):
        raise ValueError(
            f"pose problem: stereo observations (finite u_right_px) need a pinhole camera and bf > 0; got "
            f"camera_model {problem.camera_model!r}, bf = {bf:g}"
        )
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(uv)) and np.all(np.isfinite(T0))):
        raise ValueError("pose problem: xyz_w, uv_px and T_c_w_init must be finite")
    info = np.power(float(problem.scale_factor), -2.0 * level.astype(np.float64))
    chi2_max = np.where(stereo, float(problem.chi2_stereo), float(problem.chi2_mono))
    fisheye = problem.camera_model == CAMERA_KANNALA_BRANDT
    if problem.camera_model not in (CAMERA_PINHOLE, CAMERA_KANNALA_BRANDT):
        raise ValueError(f"pose problem: camera_model {problem.camera_model!r} is not supported here")
    cam = np.zeros(8)
    cam[:4] = np.asarray(problem.intrinsics, np.float64)
    if fisheye:
        if problem.distortion is None or np.shape(problem.distortion) != (4,):
            raise ValueError("pose problem: a kannala_brandt problem needs distortion k1..k4 of shape (4,)")
        cam[4:] = np.asarray(problem.distortion, np.float64)
    which, T21, cam2, fisheye2 = _second_camera(problem, n, cam, fisheye)
    T, inliers, iterations, c0, c1 = _optimize_pose_kernel(
        T0,
        X,
        uv,
        info,
        chi2_max,
        cam,
        fisheye,
        stereo,
        ur,
        bf,
        which,
        T21,
        cam2,
        fisheye2,
        _adjoint(T21),
        int(problem.rounds),
        int(problem.iterations_per_round),
        LM_TAU,
        LM_MAX_TRIALS,
        LM_REL_TOL,
    )
    return PoseOnlyResult(T_c_w=T, inliers=inliers, cost_initial=c0, cost_final=c1, iterations=iterations)
