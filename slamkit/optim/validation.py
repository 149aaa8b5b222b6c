"""Checks every backend runs on a problem before solving it.

A malformed problem (NaN/inf, wrong shapes, empty observations, indices out of range, a point behind every
camera observing it, a graph with gauge freedom, inertial terms the backend does not support) raises
:class:`slamkit.errors.ProblemError` naming the problem type, the array, the first offending index and what was
expected. The checks are vectorised: they cost a small fraction of a solve.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from slamkit.errors import ProblemError
from slamkit.problems import (
    CAMERA_MODELS,
    CAMERA_PINHOLE,
    BundleProblem,
    EssentialGraphProblem,
    PoseOnlyProblem,
    Sim3Problem,
)

__all__ = [
    "MIN_DEPTH_M",
    "validate_bundle_problem",
    "validate_essential_graph_problem",
    "validate_pose_problem",
    "validate_sim3_problem",
]

F64 = NDArray[np.float64]

#: A point is "in front of" a camera when its depth exceeds this (m); ORB-SLAM rejects z <= 0.
MIN_DEPTH_M = 1e-6
# Max |R R^T - I| accepted for a rotation block (poses are float64; this tolerates text round trips).
_ROTATION_TOL = 1e-5


def _where(problem: str, name: str) -> str:
    return f"{problem}.{name}"


def _float_array(problem: str, name: str, value: Any, shape: tuple[int | None, ...], *, allow_nan: bool = False) -> F64:
    """``value`` as float64 of ``shape`` (None = any length), finite (NaN allowed when told); else ProblemError."""
    label = _where(problem, name)
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ProblemError(f"{label}: expected a numeric array, got {type(value).__name__}") from exc
    _check_shape(label, arr, shape)
    bad = np.isinf(arr) if allow_nan else ~np.isfinite(arr)
    if bad.any():
        index = np.unravel_index(int(np.argmax(bad)), arr.shape)
        what = "inf" if allow_nan else "NaN or inf"
        first = tuple(int(i) for i in index)
        raise ProblemError(
            f"{label}: contains {what} at index {first if len(first) > 1 else first[0]} "
            f"({int(bad.sum())} bad values); expected finite values"
        )
    return arr


def _int_array(problem: str, name: str, value: Any, shape: tuple[int | None, ...]) -> NDArray[np.int64]:
    label = _where(problem, name)
    arr = np.asarray(value)
    if not np.issubdtype(arr.dtype, np.integer):
        raise ProblemError(f"{label}: expected an integer array, got dtype {arr.dtype}")
    _check_shape(label, arr, shape)
    return arr.astype(np.int64, copy=False)


def _bool_array(problem: str, name: str, value: Any, shape: tuple[int | None, ...]) -> NDArray[np.bool_]:
    label = _where(problem, name)
    arr = np.asarray(value)
    if arr.dtype != np.bool_:
        raise ProblemError(f"{label}: expected a bool array, got dtype {arr.dtype}")
    _check_shape(label, arr, shape)
    return arr


def _check_shape(label: str, arr: NDArray[Any], shape: tuple[int | None, ...]) -> None:
    ok = arr.ndim == len(shape) and all(want is None or got == want for got, want in zip(arr.shape, shape, strict=True))
    if not ok:
        expected = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
        raise ProblemError(f"{label}: expected shape {expected}, got {arr.shape}")


def _in_range(problem: str, name: str, idx: NDArray[np.int64], n: int, of: str) -> None:
    bad = (idx < 0) | (idx >= n)
    if bad.any():
        i = int(np.argmax(bad))
        raise ProblemError(
            f"{_where(problem, name)}[{i}] = {int(idx[i])} is out of range: expected an index into {of} in [0, {n})"
        )


def _levels(problem: str, name: str, value: Any, n: int) -> None:
    level = _int_array(problem, name, value, (n,))
    if (level < 0).any():
        i = int(np.argmax(level < 0))
        raise ProblemError(f"{_where(problem, name)}[{i}] = {int(level[i])}: expected a pyramid level >= 0")


def _positive(problem: str, name: str, value: Any) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError) as exc:
        raise ProblemError(f"{_where(problem, name)}: expected a number, got {value!r}") from exc
    if not (np.isfinite(x) and x > 0.0):
        raise ProblemError(f"{_where(problem, name)} = {value!r}: expected a finite number > 0")
    return x


def _count(problem: str, name: str, value: Any, minimum: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or int(value) < minimum:
        raise ProblemError(f"{_where(problem, name)} = {value!r}: expected an integer >= {minimum}")


def _intrinsics(problem: str, name: str, value: Any, shape: tuple[int | None, ...]) -> F64:
    K = _float_array(problem, name, value, shape)
    flat = K.reshape(-1, 4)
    bad = (flat[:, 0] <= 0.0) | (flat[:, 1] <= 0.0)
    if bad.any():
        i = int(np.argmax(bad))
        where = f"[{i}]" if K.ndim == 2 else ""
        raise ProblemError(
            f"{_where(problem, name)}{where} = {flat[i].tolist()}: expected (fx, fy, cx, cy) with fx, fy > 0"
        )
    return K


def _check_rotations(label: str, A: F64, scaled: bool) -> None:
    """A: (K, 3, 3) blocks that must be R (or s R with s > 0 when ``scaled``)."""
    det = np.linalg.det(A)
    if (det <= 0.0).any():
        k = int(np.argmax(det <= 0.0))
        raise ProblemError(f"{label}[{k}]: rotation block has det {det[k]:.6g}; expected a proper rotation")
    s = np.cbrt(det) if scaled else np.ones_like(det)
    R = A / s[:, None, None]
    err = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max(axis=(1, 2))
    if not scaled:
        err = np.maximum(err, np.abs(det - 1.0))
    bad = err > _ROTATION_TOL
    if bad.any():
        k = int(np.argmax(bad))
        kind = "s R (a similarity)" if scaled else "a rotation"
        raise ProblemError(f"{label}[{k}]: the 3x3 block is not {kind} (orthonormality error {err[k]:.3g})")


def _transforms(problem: str, name: str, value: Any, n: int | None, *, scaled: bool) -> F64:
    """(n, 4, 4) rigid (or Sim3 when ``scaled``) matrices; a single (4, 4) when n is None is handled by callers."""
    M = _float_array(problem, name, value, (n, 4, 4))
    label = _where(problem, name)
    last = np.abs(M[:, 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=1) if len(M) else np.zeros(0)
    if (last > 1e-9).any():
        k = int(np.argmax(last > 1e-9))
        raise ProblemError(f"{label}[{k}]: expected last row [0, 0, 0, 1], got {M[k, 3].tolist()}")
    _check_rotations(label, M[:, :3, :3], scaled)
    return M


def _transform(problem: str, name: str, value: Any, *, scaled: bool) -> F64:
    M = _float_array(problem, name, value, (4, 4))
    out = _transforms(problem, name, M[None], 1, scaled=scaled)
    return out[0]


def _stereo(problem: str, u_right: F64, bf_per_obs: F64) -> None:
    """Stereo observations (finite u_right) need bf > 0 and a non-negative disparity."""
    stereo = np.isfinite(u_right)
    bad = stereo & (bf_per_obs <= 0.0)
    if bad.any():
        i = int(np.argmax(bad))
        raise ProblemError(
            f"{problem}.u_right_px[{i}] is a stereo observation but bf = {bf_per_obs[i]:.6g} for its camera; "
            "expected bf = baseline * fx > 0 (or NaN u_right_px for a monocular observation)"
        )


def _camera_model(problem: str, model: Any, distortion: Any, shape: tuple[int, ...], u_right: F64) -> None:
    """``camera_model`` is a known model; a pinhole problem has no ``distortion`` (its observations are undistorted),
    a Kannala-Brandt one has finite k1..k4 of ``shape`` and no stereo observation (no rectified right image)."""
    if model not in CAMERA_MODELS:
        raise ProblemError(f"{problem}.camera_model = {model!r}: expected one of {', '.join(CAMERA_MODELS)}")
    if model == CAMERA_PINHOLE:
        if distortion is not None:
            raise ProblemError(
                f"{problem}.distortion: given for a pinhole problem, whose observations are undistorted; expected None"
            )
        return
    if distortion is None:
        raise ProblemError(f"{problem}.distortion: missing; expected k1..k4 of shape {shape} for a {model} camera")
    _float_array(problem, "distortion", distortion, shape)
    stereo = np.isfinite(u_right)
    if stereo.any():
        i = int(np.argmax(stereo))
        raise ProblemError(
            f"{problem}.u_right_px[{i}] is a stereo observation in a {model} problem; expected NaN (a rectified "
            "right coordinate exists for pinhole cameras only)"
        )


def _inertial(problem: str, inertial: object, supports_inertial: bool, backend: str) -> None:
    if inertial is not None and not supports_inertial:
        raise ProblemError(
            f"{problem}.inertial: the problem carries inertial terms, which the {backend} backend does not support"
        )


def _second_camera(
    p: str, problem: PoseOnlyProblem | BundleProblem, n: int, u_right: F64, supports_rig: bool, backend: str
) -> None:
    """A two-camera rig's fields: camera_index (N,) of 0 / 1; with any 1, a backend that supports it, a rigid
    T_c2_c1, intrinsics2, a known camera_model2 with its distortion2, and no right coordinate on those observations
    (a pose problem: one of each; a bundle problem: one per keyframe)."""
    if problem.camera_index is None:
        return
    which = _int_array(p, "camera_index", problem.camera_index, (n,))
    if not np.isin(which, (0, 1)).all():
        i = int(np.argmax(~np.isin(which, (0, 1))))
        raise ProblemError(f"{p}.camera_index[{i}] = {which[i]}: expected 0 (the pose's camera) or 1 (the second)")
    second = which == 1
    if not second.any():
        return
    if not supports_rig:
        raise ProblemError(
            f"{p}.camera_index: the problem has second-camera observations (a non-rectified stereo rig), which the "
            f"{backend} backend does not support yet; use the compiled pose optimization "
            "(pipeline.tracking.pose_optimization=compiled)"
        )
    if problem.T_c2_c1 is None or problem.intrinsics2 is None:
        raise ProblemError(f"{p}: second-camera observations need T_c2_c1 and intrinsics2")
    if isinstance(problem, BundleProblem):
        K = len(problem.T_c_w)
        _transforms(p, "T_c2_c1", problem.T_c2_c1, K, scaled=False)
        _intrinsics(p, "intrinsics2", problem.intrinsics2, (K, 4))
        shape: tuple[int, ...] = (K, 4)
    else:
        _transform(p, "T_c2_c1", problem.T_c2_c1, scaled=False)
        _intrinsics(p, "intrinsics2", problem.intrinsics2, (4,))
        shape = (4,)
    _camera_model(p, problem.camera_model2, problem.distortion2, shape, np.where(second, u_right, np.nan))


def validate_pose_problem(problem: PoseOnlyProblem, *, supports_rig: bool = False, backend: str = "this") -> None:
    """Check a motion-only BA problem; raise ProblemError naming the first defect.

    Requires at least one observation, finite arrays of matching lengths (u_right_px may be NaN = monocular),
    a rigid T_c_w_init, fx, fy > 0, bf > 0 when any observation is stereo, a known camera model (k1..k4 for
    Kannala-Brandt, which has no stereo observations), and at least one point in front of
    the initial camera (points behind it are allowed: they end up classified as outliers). Observations of a second
    camera (``camera_index`` 1) need ``supports_rig`` and the second camera's fields (no right coordinate).
    """
    p = "PoseOnlyProblem"
    T = _transform(p, "T_c_w_init", problem.T_c_w_init, scaled=False)
    xyz = _float_array(p, "xyz_w", problem.xyz_w, (None, 3))
    n = len(xyz)
    if n == 0:
        raise ProblemError(f"{p}: no observations (xyz_w is empty); expected at least one observed point")
    _float_array(p, "uv_px", problem.uv_px, (n, 2))
    u_right = _float_array(p, "u_right_px", problem.u_right_px, (n,), allow_nan=True)
    _levels(p, "level", problem.level, n)
    _intrinsics(p, "intrinsics", problem.intrinsics, (4,))
    bf = float(problem.bf)
    if not np.isfinite(bf) or bf < 0.0:
        raise ProblemError(f"{p}.bf = {problem.bf!r}: expected a finite number >= 0")
    _stereo(p, u_right, np.full(n, bf))
    _camera_model(p, problem.camera_model, problem.distortion, (4,), u_right)
    _second_camera(p, problem, n, u_right, supports_rig, backend)
    _positive(p, "scale_factor", problem.scale_factor)
    _positive(p, "chi2_mono", problem.chi2_mono)
    _positive(p, "chi2_stereo", problem.chi2_stereo)
    _count(p, "rounds", problem.rounds, 1)
    _count(p, "iterations_per_round", problem.iterations_per_round, 1)
    z = xyz @ T[2, :3] + T[2, 3]
    if not (z > MIN_DEPTH_M).any():
        raise ProblemError(
            f"{p}: every one of the {n} points is behind the initial camera T_c_w_init (max depth {z.max():.3g} m); "
            "expected points in front of it"
        )


def validate_bundle_problem(
    problem: BundleProblem, *, supports_inertial: bool = False, supports_rig: bool = False, backend: str = "this"
) -> None:
    """Check a bundle-adjustment problem; raise ProblemError naming the first defect.

    Requires K >= 1 poses, M >= 1 points and E >= 1 observations, finite arrays of consistent shapes, rigid
    poses, indices in range, fx, fy > 0 per keyframe, bf > 0 for keyframes with stereo observations, a known
    camera model (k1..k4 per keyframe for Kannala-Brandt, which has no stereo observations), every
    free pose and free point observed at least once, every point in front (initial guess) of at least one
    camera observing it, at least one fixed variable (a fixed pose or point: otherwise the gauge is free), and
    no inertial terms unless ``supports_inertial``, and second-camera observations (``camera_index`` 1) only with
    ``supports_rig`` and the rig's fields.
    """
    p = "BundleProblem"
    _inertial(p, problem.inertial, supports_inertial, backend)
    T = _transforms(p, "T_c_w", problem.T_c_w, None, scaled=False)
    K = len(T)
    if K == 0:
        raise ProblemError(f"{p}.T_c_w: no keyframe poses; expected at least one")
    pose_fixed = _bool_array(p, "pose_fixed", problem.pose_fixed, (K,))
    _intrinsics(p, "intrinsics", problem.intrinsics, (K, 4))
    bf = _float_array(p, "bf", problem.bf, (K,))
    if (bf < 0.0).any():
        k = int(np.argmax(bf < 0.0))
        raise ProblemError(f"{p}.bf[{k}] = {bf[k]:.6g}: expected baseline * fx >= 0")
    xyz = _float_array(p, "xyz_w", problem.xyz_w, (None, 3))
    M = len(xyz)
    if M == 0:
        raise ProblemError(f"{p}.xyz_w: no points; expected at least one")
    point_fixed = _bool_array(p, "point_fixed", problem.point_fixed, (M,))
    obs_pose = _int_array(p, "obs_pose", problem.obs_pose, (None,))
    E = len(obs_pose)
    if E == 0:
        raise ProblemError(f"{p}: no observations (obs_pose is empty); expected at least one")
    obs_point = _int_array(p, "obs_point", problem.obs_point, (E,))
    _float_array(p, "uv_px", problem.uv_px, (E, 2))
    u_right = _float_array(p, "u_right_px", problem.u_right_px, (E,), allow_nan=True)
    _levels(p, "level", problem.level, E)
    _in_range(p, "obs_pose", obs_pose, K, "T_c_w")
    _in_range(p, "obs_point", obs_point, M, "xyz_w")
    _stereo(p, u_right, bf[obs_pose])
    _camera_model(p, problem.camera_model, problem.distortion, (K, 4), u_right)
    _second_camera(p, problem, E, u_right, supports_rig, backend)
    _positive(p, "scale_factor", problem.scale_factor)
    _positive(p, "chi2_mono", problem.chi2_mono)
    _positive(p, "chi2_stereo", problem.chi2_stereo)
    _count(p, "iterations_first", problem.iterations_first, 0)
    _count(p, "iterations_second", problem.iterations_second, 0)
    if not (pose_fixed.any() or point_fixed.any()):
        raise ProblemError(
            f"{p}: no fixed variable (pose_fixed and point_fixed are all False): the gauge (global pose) is free; "
            "expected at least one fixed keyframe"
        )
    pose_seen = np.bincount(obs_pose, minlength=K) > 0
    unseen = ~pose_fixed & ~pose_seen
    if unseen.any():
        k = int(np.argmax(unseen))
        raise ProblemError(f"{p}: free pose {k} has no observations; expected every free pose to be observed")
    point_seen = np.bincount(obs_point, minlength=M) > 0
    unseen = ~point_fixed & ~point_seen
    if unseen.any():
        j = int(np.argmax(unseen))
        raise ProblemError(f"{p}: free point {j} has no observations; expected every free point to be observed")
    # Depth of each observed point in its observing camera (initial guess): z = R[2] . x + t[2].
    z = np.einsum("ij,ij->i", T[obs_pose, 2, :3], xyz[obs_point]) + T[obs_pose, 2, 3]
    in_front = np.bincount(obs_point, weights=(z > MIN_DEPTH_M).astype(np.float64), minlength=M) > 0
    behind = point_seen & ~in_front
    if behind.any():
        j = int(np.argmax(behind))
        cams = obs_pose[obs_point == j][:5].tolist()
        raise ProblemError(
            f"{p}: point {j} (xyz_w = {xyz[j].tolist()}) is behind every camera observing it "
            f"(keyframes {cams}...); expected positive depth in at least one"
        )


def validate_sim3_problem(problem: Sim3Problem) -> None:
    """Check a relative-Sim3 problem; raise ProblemError naming the first defect.

    Requires N >= 3 matches (a Sim3 has 7 degrees of freedom), finite arrays of matching lengths, a valid
    Sim3 S_12_init ([[s R, t], [0, 1]], s > 0; s = 1 when fix_scale), fx, fy > 0, each keyframe's camera model known
    (a Kannala-Brandt one with its k1..k4), and each match's points in front of their own cameras (xyz1_c1 and
    xyz2_c2 have z > 0).
    """
    p = "Sim3Problem"
    S = _transform(p, "S_12_init", problem.S_12_init, scaled=True)
    xyz1 = _float_array(p, "xyz1_c1", problem.xyz1_c1, (None, 3))
    n = len(xyz1)
    if n < 3:
        raise ProblemError(f"{p}: {n} matches (xyz1_c1 has {n} rows); expected at least 3 to determine a Sim3")
    xyz2 = _float_array(p, "xyz2_c2", problem.xyz2_c2, (n, 3))
    _float_array(p, "uv1_px", problem.uv1_px, (n, 2))
    _float_array(p, "uv2_px", problem.uv2_px, (n, 2))
    _levels(p, "level1", problem.level1, n)
    _levels(p, "level2", problem.level2, n)
    _intrinsics(p, "intrinsics1", problem.intrinsics1, (4,))
    _intrinsics(p, "intrinsics2", problem.intrinsics2, (4,))
    no_right = np.full(n, np.nan)
    _camera_model(f"{p} (keyframe 1)", problem.camera_model1, problem.distortion1, (4,), no_right)
    _camera_model(f"{p} (keyframe 2)", problem.camera_model2, problem.distortion2, (4,), no_right)
    _positive(p, "scale_factor", problem.scale_factor)
    _positive(p, "chi2", problem.chi2)
    _count(p, "iterations_first", problem.iterations_first, 0)
    _count(p, "iterations_second", problem.iterations_second, 0)
    if problem.fix_scale:
        s = float(np.cbrt(np.linalg.det(S[:3, :3])))
        if abs(s - 1.0) > 1e-6:
            raise ProblemError(f"{p}.S_12_init has scale {s:.6g} but fix_scale is True; expected scale 1")
    for name, pts in (("xyz1_c1", xyz1), ("xyz2_c2", xyz2)):
        behind = pts[:, 2] <= MIN_DEPTH_M
        if behind.any():
            i = int(np.argmax(behind))
            raise ProblemError(
                f"{p}.{name}[{i}] = {pts[i].tolist()} is behind its camera (z <= 0); expected points in front"
            )


def validate_essential_graph_problem(problem: EssentialGraphProblem) -> None:
    """Check an essential-graph problem; raise ProblemError naming the first defect.

    Requires K >= 2 poses and E >= 1 edges, valid Sim3 matrices (rigid when use_sim3 is False), edge indices
    in range with i != j, positive finite weights, at least one fixed keyframe, and every keyframe connected
    through edges to a fixed one (a component without a fixed keyframe has a free gauge).
    """
    p = "EssentialGraphProblem"
    scaled = bool(problem.use_sim3)
    S = _transforms(p, "S_c_w", problem.S_c_w, None, scaled=scaled)
    K = len(S)
    if K < 2:
        raise ProblemError(f"{p}.S_c_w: {K} keyframes; expected at least 2")
    fixed = _bool_array(p, "fixed", problem.fixed, (K,))
    edge_i = _int_array(p, "edge_i", problem.edge_i, (None,))
    E = len(edge_i)
    if E == 0:
        raise ProblemError(f"{p}: no edges (edge_i is empty); expected at least one")
    edge_j = _int_array(p, "edge_j", problem.edge_j, (E,))
    _in_range(p, "edge_i", edge_i, K, "S_c_w")
    _in_range(p, "edge_j", edge_j, K, "S_c_w")
    self_loop = edge_i == edge_j
    if self_loop.any():
        e = int(np.argmax(self_loop))
        raise ProblemError(f"{p}: edge {e} joins keyframe {int(edge_i[e])} to itself; expected i != j")
    _transforms(p, "S_ij", problem.S_ij, E, scaled=scaled)
    if problem.weights is not None:
        w = _float_array(p, "weights", problem.weights, (E,))
        if (w <= 0.0).any():
            e = int(np.argmax(w <= 0.0))
            raise ProblemError(f"{p}.weights[{e}] = {w[e]:.6g}: expected weights > 0")
    _count(p, "iterations", problem.iterations, 1)
    if not fixed.any():
        raise ProblemError(
            f"{p}: no fixed keyframe (fixed is all False): the gauge is free; expected the loop keyframe fixed"
        )
    graph = coo_matrix((np.ones(E), (edge_i, edge_j)), shape=(K, K))
    n_comp, labels = connected_components(graph, directed=False)
    anchored = np.zeros(n_comp, dtype=bool)
    anchored[labels[fixed]] = True
    free = ~anchored[labels]
    if free.any():
        k = int(np.argmax(free))
        raise ProblemError(
            f"{p}: keyframe {k} is not connected by edges to any fixed keyframe ({int(free.sum())} such keyframes): "
            "its gauge is free; expected a connected graph with a fixed keyframe"
        )
