"""Seeded optimization problems with known truth, pixel noise and planted outliers (tests and benchmarks).

Each ``make_*`` takes a ``numpy.random.Generator`` and returns ``(problem, truth)``. The geometry follows a
640x480 camera (fx = fy = 520 px, cx = 320, cy = 240; stereo baseline 0.12 m, so bf = 62.4 m px) looking at
points a few metres in front of it. Keypoints get ORB pyramid levels 0..7 (scale 1.2), drawn as ORB-SLAM
distributes features over levels (a share proportional to 1.2^-level), and their pixel noise has standard
deviation ``noise_px * 1.2**level``: exactly the information ORB-SLAM assumes, so the chi-square gates
behave as in the paper (about 5 % of clean monocular observations exceed 5.991).

Planted outliers are wrong matches: their pixels are displaced by 15 to 40 standard deviations of their
level (so any correct solver flags them); ``truth.outlier`` marks them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import overload

import numpy as np
from numpy.typing import NDArray

from slamkit.geometry.so3 import so3_exp
from slamkit.optim.costs import kannala_brandt_project
from slamkit.problems import CAMERA_KANNALA_BRANDT, BundleProblem, EssentialGraphProblem, PoseOnlyProblem, Sim3Problem

__all__ = [
    "BASELINE_M",
    "FISHEYE_K",
    "IMAGE_SIZE",
    "INTRINSICS",
    "N_LEVELS",
    "SCALE_FACTOR",
    "BundleTruth",
    "EssentialGraphTruth",
    "PoseTruth",
    "Sim3Truth",
    "look_at",
    "make_bundle_problem",
    "make_essential_graph_problem",
    "make_pose_problem",
    "make_sim3_problem",
    "pose_errors",
    "project",
    "sim3_errors",
    "with_kannala_brandt",
]

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
B = NDArray[np.bool_]

#: fx, fy, cx, cy (px) of the synthetic 640x480 camera.
INTRINSICS = np.array([520.0, 520.0, 320.0, 240.0])
IMAGE_SIZE = (640, 480)
#: Stereo baseline (m); bf = BASELINE_M * fx.
BASELINE_M = 0.12
N_LEVELS = 8  # ORB-SLAM sec. III-A: 8 pyramid levels
SCALE_FACTOR = 1.2  # ORB-SLAM sec. III-A: scale factor 1.2 between levels
_MARGIN_PX = 10.0
#: k1..k4 of the fisheye problems: ORB-SLAM3's TUM-VI KannalaBrandt8 calibration, with the synthetic intrinsics.
FISHEYE_K = np.array([0.0034823894022493434, 0.0007150348452162257, -0.0020532361418706202, 0.00020293673591811182])
_OUTLIER_SIGMAS = (15.0, 40.0)


@dataclass
class PoseTruth:
    """T_c_w: (4, 4) true pose; outlier: (N,) bool, the planted wrong matches."""

    T_c_w: F64
    outlier: B


@dataclass
class BundleTruth:
    """T_c_w: (K, 4, 4) true poses; xyz_w: (M, 3) m true points; outlier: (E,) bool planted wrong matches."""

    T_c_w: F64
    xyz_w: F64
    outlier: B


@dataclass
class Sim3Truth:
    """S_12: (4, 4) true Sim3 (camera 2 -> camera 1); outlier: (N,) bool planted wrong matches."""

    S_12: F64
    outlier: B


@dataclass
class EssentialGraphTruth:
    """S_c_w: (K, 4, 4) true poses (scale 1); loop_edges: indices of the loop-closing edges in the edge arrays."""

    S_c_w: F64
    loop_edges: I64


# ---- geometry helpers -------------------------------------------------------------------------------


def look_at(position_w: F64, target_w: F64, up_w: F64 | None = None) -> F64:
    """(4, 4) T_c_w of a camera at ``position_w`` looking at ``target_w`` (x right, y down, z forward; world z up)."""
    up = np.array([0.0, 0.0, 1.0]) if up_w is None else np.asarray(up_w, dtype=np.float64)
    z = np.asarray(target_w, dtype=np.float64) - np.asarray(position_w, dtype=np.float64)
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    R_w_c = np.stack([x, y, z], axis=1)
    T = np.eye(4)
    T[:3, :3] = R_w_c.T
    T[:3, 3] = -R_w_c.T @ np.asarray(position_w, dtype=np.float64)
    return T


def project(T_c_w: F64, xyz_w: F64, intrinsics: F64) -> tuple[F64, F64]:
    """Pinhole projection. T_c_w: (4, 4) or (N, 4, 4); xyz_w: (N, 3) -> (uv (N, 2) px, depth z (N,) m)."""
    if T_c_w.ndim == 2:
        xyz_c = xyz_w @ T_c_w[:3, :3].T + T_c_w[:3, 3]
    else:
        xyz_c = np.einsum("nij,nj->ni", T_c_w[:, :3, :3], xyz_w) + T_c_w[:, :3, 3]
    K = np.asarray(intrinsics, dtype=np.float64)
    fx, fy, cx, cy = (K[..., i] for i in range(4))
    z = xyz_c[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([fx * xyz_c[:, 0] / z + cx, fy * xyz_c[:, 1] / z + cy], axis=1)
    return uv, z


def _in_image(uv: F64, z: F64) -> B:
    w, h = IMAGE_SIZE
    out: B = (
        (z > 0.1)
        & (uv[:, 0] >= _MARGIN_PX)
        & (uv[:, 0] <= w - _MARGIN_PX)
        & (uv[:, 1] >= _MARGIN_PX)
        & (uv[:, 1] <= h - _MARGIN_PX)
    )
    return out


def _backproject(uv: F64, depth: F64, intrinsics: F64) -> F64:
    fx, fy, cx, cy = intrinsics
    return np.stack([(uv[:, 0] - cx) / fx * depth, (uv[:, 1] - cy) / fy * depth, depth], axis=1)


def _random_levels(rng: np.random.Generator, n: int) -> I64:
    share = SCALE_FACTOR ** -np.arange(N_LEVELS, dtype=np.float64)
    return rng.choice(N_LEVELS, size=n, p=share / share.sum()).astype(np.int64)


def _sigma(level: I64) -> F64:
    out: F64 = SCALE_FACTOR ** level.astype(np.float64)
    return out


def _random_pixels(rng: np.random.Generator, n: int) -> F64:
    w, h = IMAGE_SIZE
    return np.stack([rng.uniform(_MARGIN_PX, w - _MARGIN_PX, n), rng.uniform(_MARGIN_PX, h - _MARGIN_PX, n)], axis=1)


def _outlier_offsets(rng: np.random.Generator, sigma: F64) -> F64:
    """(n, 2) displacements of 15..40 standard deviations in random directions."""
    angle = rng.uniform(0.0, 2.0 * np.pi, len(sigma))
    size = rng.uniform(*_OUTLIER_SIGMAS, len(sigma)) * sigma
    return np.stack([np.cos(angle), np.sin(angle)], axis=1) * size[:, None]


def _perturb_pose(rng: np.random.Generator, T: F64, rot_rad: float, trans_m: float) -> F64:
    """T (4, 4) or (K, 4, 4) composed on the left with a random rotation (rot_rad per axis) and translation."""
    batch = T.reshape(-1, 4, 4)
    n = len(batch)
    D = np.tile(np.eye(4), (n, 1, 1))
    D[:, :3, :3] = so3_exp(rng.normal(0.0, rot_rad, (n, 3)))
    D[:, :3, 3] = rng.normal(0.0, trans_m, (n, 3))
    return (D @ batch).reshape(T.shape)


def _planted(rng: np.random.Generator, n: int, ratio: float, allowed: B | None = None) -> B:
    """(n,) mask with round(ratio * n) True entries drawn among ``allowed`` (all when None)."""
    if not 0.0 <= ratio < 0.5:
        raise ValueError(f"outlier_ratio = {ratio}: expected a value in [0, 0.5)")
    pool = np.flatnonzero(np.ones(n, dtype=bool) if allowed is None else allowed)
    k = min(round(ratio * n), len(pool))
    mask = np.zeros(n, dtype=bool)
    mask[rng.choice(pool, size=k, replace=False)] = True
    return mask


# ---- motion-only BA -----------------------------------------------------------------------------------


def make_pose_problem(
    rng: np.random.Generator,
    n_points: int = 300,
    noise_px: float = 1.0,
    outlier_ratio: float = 0.03,
    stereo_ratio: float = 0.0,
    init_rot_rad: float = 0.02,
    init_trans_m: float = 0.1,
) -> tuple[PoseOnlyProblem, PoseTruth]:
    """One camera looking at ``n_points`` points 2..8 m in front of it (tracking's pose optimization).

    stereo_ratio: share of observations with a right-image u (the rest are monocular, NaN).
    init_rot_rad / init_trans_m: std of the initial guess's error per axis (a motion-model prediction).
    """
    position = rng.uniform(-5.0, 5.0, 3)
    target = position + np.array([np.cos(a := rng.uniform(0, 2 * np.pi)), np.sin(a), rng.uniform(-0.2, 0.2)])
    T_true = look_at(position, target)
    uv_true = _random_pixels(rng, n_points)
    depth = rng.uniform(2.0, 8.0, n_points)
    xyz_c = _backproject(uv_true, depth, INTRINSICS)
    T_w_c = np.linalg.inv(T_true)
    xyz_w = xyz_c @ T_w_c[:3, :3].T + T_w_c[:3, 3]
    level = _random_levels(rng, n_points)
    sigma = noise_px * _sigma(level)
    uv = uv_true + rng.normal(0.0, 1.0, (n_points, 2)) * sigma[:, None]
    bf = BASELINE_M * INTRINSICS[0]
    u_right = np.full(n_points, np.nan)
    stereo = rng.random(n_points) < stereo_ratio
    u_right[stereo] = uv_true[stereo, 0] - bf / depth[stereo] + rng.normal(0.0, 1.0, int(stereo.sum())) * sigma[stereo]
    outlier = _planted(rng, n_points, outlier_ratio)
    offsets = _outlier_offsets(rng, _sigma(level[outlier]) * max(noise_px, 1.0))
    uv[outlier] += offsets
    u_right[outlier] += offsets[:, 0]
    problem = PoseOnlyProblem(
        T_c_w_init=_perturb_pose(rng, T_true, init_rot_rad, init_trans_m),
        xyz_w=xyz_w,
        uv_px=uv,
        u_right_px=u_right,
        level=level,
        intrinsics=INTRINSICS.copy(),
        bf=bf,
        scale_factor=SCALE_FACTOR,
    )
    return problem, PoseTruth(T_c_w=T_true, outlier=outlier)


# ---- bundle adjustment --------------------------------------------------------------------------------


def _ba_cameras(rng: np.random.Generator, n: int) -> F64:
    """(n, 4, 4) T_c_w of keyframes along a 3 m sideways path at 1.5 m height, all facing a scene ~5 m ahead."""
    ys = np.linspace(-1.5, 1.5, n) + rng.normal(0.0, 0.05, n)
    out = np.empty((n, 4, 4))
    for k, y in enumerate(ys):
        position = np.array([rng.normal(0.0, 0.2), y, 1.5 + rng.normal(0.0, 0.1)])
        target = np.array([5.0, 0.5 * y, 1.5]) + rng.normal(0.0, 0.3, 3)
        out[k] = look_at(position, target)
    return out


def make_bundle_problem(
    rng: np.random.Generator,
    n_free: int = 10,
    n_fixed: int = 10,
    n_points: int = 2000,
    n_obs: int = 20000,
    noise_px: float = 1.0,
    outlier_ratio: float = 0.02,
    stereo_ratio: float = 0.0,
    init_rot_rad: float = 0.005,
    init_trans_m: float = 0.03,
    init_point_m: float = 0.05,
) -> tuple[BundleProblem, BundleTruth]:
    """A local BA: ``n_fixed`` fixed keyframes (exact) and ``n_free`` free ones (perturbed), ``n_points`` free points
    (perturbed by ``init_point_m`` per axis) at 2..8 m, observed ``n_obs`` times (each point at least twice).

    Fixed keyframes come first in the arrays. Planted outliers are chosen among observations of points seen at
    least three times, so every point keeps two clean observations. Raises ValueError when the cameras do not see
    enough (point, keyframe) pairs for ``n_obs``.
    """
    K = n_free + n_fixed
    if n_free < 1 or n_fixed < 1:
        raise ValueError(f"n_free = {n_free}, n_fixed = {n_fixed}: expected at least one of each")
    T_true = _ba_cameras(rng, K)
    # Points: a pixel and a depth in a random keyframe, kept when at least 3 keyframes see it.
    cand = 3 * n_points
    anchor = rng.integers(0, K, cand)
    xyz_c = _backproject(_random_pixels(rng, cand), rng.uniform(2.0, 8.0, cand), INTRINSICS)
    T_w_c = np.linalg.inv(T_true[anchor])
    xyz_all = np.einsum("nij,nj->ni", T_w_c[:, :3, :3], xyz_c) + T_w_c[:, :3, 3]
    vis = np.empty((K, cand), dtype=bool)
    for k in range(K):
        uv, z = project(T_true[k], xyz_all, INTRINSICS)
        vis[k] = _in_image(uv, z)
    keep = np.flatnonzero(vis.sum(axis=0) >= 3)
    if len(keep) < n_points:
        raise ValueError(f"only {len(keep)} of {cand} candidate points are seen by 3 keyframes; need {n_points}")
    keep = keep[:n_points]
    xyz_true = xyz_all[keep]
    vis = vis[:, keep]
    pair_pose, pair_point = np.nonzero(vis)
    if len(pair_pose) < n_obs:
        raise ValueError(f"the keyframes see only {len(pair_pose)} (keyframe, point) pairs; n_obs = {n_obs}")
    # Each point's two pairs with the smallest random keys are kept; the rest are drawn at random.
    key = rng.random(len(pair_pose))
    order = np.lexsort((key, pair_point))
    starts = np.searchsorted(pair_point[order], np.arange(n_points))
    rank = np.empty(len(order), dtype=np.int64)
    rank[order] = np.arange(len(order)) - starts[pair_point[order]]
    mandatory = rank < 2
    rest = np.flatnonzero(~mandatory)
    extra = rng.choice(rest, size=n_obs - int(mandatory.sum()), replace=False)
    chosen = np.sort(np.concatenate([np.flatnonzero(mandatory), extra]))
    obs_pose = pair_pose[chosen].astype(np.int64)
    obs_point = pair_point[chosen].astype(np.int64)
    E = len(obs_pose)

    uv_true, depth = project(T_true[obs_pose], xyz_true[obs_point], INTRINSICS)
    level = _random_levels(rng, E)
    sigma = noise_px * _sigma(level)
    uv = uv_true + rng.normal(0.0, 1.0, (E, 2)) * sigma[:, None]
    bf = BASELINE_M * INTRINSICS[0]
    u_right = np.full(E, np.nan)
    stereo = rng.random(E) < stereo_ratio
    u_right[stereo] = uv_true[stereo, 0] - bf / depth[stereo] + rng.normal(0.0, 1.0, int(stereo.sum())) * sigma[stereo]
    # At most one planted outlier per point (one random observation of each point seen >= 3 times is a
    # candidate), so every point keeps >= 2 clean observations.
    seen = np.bincount(obs_point, minlength=n_points)
    pick = np.lexsort((rng.random(E), obs_point))
    last_of_point = np.r_[obs_point[pick][1:] != obs_point[pick][:-1], True]
    candidate = np.zeros(E, dtype=bool)
    candidate[pick[last_of_point]] = True
    candidate &= seen[obs_point] >= 3
    outlier = _planted(rng, E, outlier_ratio, allowed=candidate)
    offsets = _outlier_offsets(rng, _sigma(level[outlier]) * max(noise_px, 1.0))
    uv[outlier] += offsets
    u_right[outlier] += offsets[:, 0]

    pose_fixed = np.zeros(K, dtype=bool)
    pose_fixed[:n_fixed] = True
    T_init = T_true.copy()
    T_init[~pose_fixed] = _perturb_pose(rng, T_true[~pose_fixed], init_rot_rad, init_trans_m)
    problem = BundleProblem(
        T_c_w=T_init,
        pose_fixed=pose_fixed,
        intrinsics=np.tile(INTRINSICS, (K, 1)),
        bf=np.full(K, bf),
        xyz_w=xyz_true + rng.normal(0.0, init_point_m, xyz_true.shape),
        point_fixed=np.zeros(n_points, dtype=bool),
        obs_pose=obs_pose,
        obs_point=obs_point,
        uv_px=uv,
        u_right_px=u_right,
        level=level,
        scale_factor=SCALE_FACTOR,
    )
    return problem, BundleTruth(T_c_w=T_true, xyz_w=xyz_true, outlier=outlier)


# ---- fisheye (Kannala-Brandt) problems ------------------------------------------------------------------


@overload
def with_kannala_brandt(problem: PoseOnlyProblem, truth: PoseTruth, k: F64 = ...) -> PoseOnlyProblem: ...


@overload
def with_kannala_brandt(problem: BundleProblem, truth: BundleTruth, k: F64 = ...) -> BundleProblem: ...


@overload
def with_kannala_brandt(problem: Sim3Problem, truth: Sim3Truth, k: F64 = ...) -> Sim3Problem: ...


def with_kannala_brandt(
    problem: PoseOnlyProblem | BundleProblem | Sim3Problem,
    truth: PoseTruth | BundleTruth | Sim3Truth,
    k: F64 = FISHEYE_K,
) -> PoseOnlyProblem | BundleProblem | Sim3Problem:
    """The same problem seen through a Kannala-Brandt lens with k1..k4 ``k`` (4,) and the same intrinsics: each
    observation becomes the raw fisheye pixel of its true point plus the same noise and planted offset the pinhole
    observation had. Monocular problems only (a fisheye camera has no rectified right image). A Sim3 problem's
    keyframes both get the lens (its fixed points are the true ones: uv1 observes xyz1_c1, uv2 the direction of
    xyz2_c2)."""
    if isinstance(problem, Sim3Problem):
        dist = np.asarray(k, dtype=np.float64).copy()
        raw: list[F64] = []
        for xyz, obs, intr in (
            (problem.xyz1_c1, problem.uv1_px, problem.intrinsics1),
            (problem.xyz2_c2, problem.uv2_px, problem.intrinsics2),
        ):
            n = len(xyz)
            pin, _ = project(np.eye(4), xyz, intr)
            u, v = kannala_brandt_project(xyz, np.broadcast_to(intr, (n, 4)), np.broadcast_to(dist, (n, 4)))
            raw.append(np.stack([u, v], axis=1) + (obs - pin))
        return replace(
            problem,
            uv1_px=raw[0],
            uv2_px=raw[1],
            camera_model1=CAMERA_KANNALA_BRANDT,
            distortion1=dist,
            camera_model2=CAMERA_KANNALA_BRANDT,
            distortion2=dist.copy(),
        )
    if np.any(np.isfinite(problem.u_right_px)):
        raise ValueError("with_kannala_brandt: the problem has stereo observations; expected a monocular one")
    if isinstance(problem, PoseOnlyProblem):
        assert isinstance(truth, PoseTruth)
        T = np.broadcast_to(truth.T_c_w, (len(problem.xyz_w), 4, 4))
        xyz = problem.xyz_w  # fixed points: the truth
        intr = np.broadcast_to(problem.intrinsics, (len(xyz), 4))
        distortion = np.asarray(k, dtype=np.float64).copy()
    else:
        assert isinstance(truth, BundleTruth)
        T = truth.T_c_w[problem.obs_pose]
        xyz = truth.xyz_w[problem.obs_point]
        intr = problem.intrinsics[problem.obs_pose]
        distortion = np.tile(np.asarray(k, dtype=np.float64), (len(problem.T_c_w), 1))
    xyz_c = np.einsum("nij,nj->ni", T[:, :3, :3], xyz) + T[:, :3, 3]
    uv_pinhole, _ = project(T, xyz, intr)
    u, v = kannala_brandt_project(xyz_c, intr, np.broadcast_to(distortion.reshape(-1, 4)[0], (len(xyz), 4)))
    uv = np.stack([u, v], axis=1) + (problem.uv_px - uv_pinhole)
    return replace(problem, uv_px=uv, camera_model=CAMERA_KANNALA_BRANDT, distortion=distortion)


# ---- relative Sim3 -------------------------------------------------------------------------------------


def _sim3_matrix(s: float, R: F64, t: F64) -> F64:
    S = np.eye(4)
    S[:3, :3] = s * R
    S[:3, 3] = t
    return S


def make_sim3_problem(
    rng: np.random.Generator,
    n_matches: int = 200,
    noise_px: float = 1.0,
    outlier_ratio: float = 0.03,
    fix_scale: bool = False,
    scale: float = 1.4,
    init_rot_rad: float = 0.02,
    init_trans_m: float = 0.05,
    init_log_scale: float = 0.05,
) -> tuple[Sim3Problem, Sim3Truth]:
    """Loop-closure Sim3 between keyframe 1 and keyframe 2 (~0.3..1 m apart, views 5..15 degrees apart).

    Keyframe 2's map has drifted in scale: its points are ``scale`` times the metric ones (1 when fix_scale), so
    the true S_12 = (scale T_21)^-1. Each match's points are exact (fixed in the problem); pixels are noisy;
    wrong matches pair the keyframe-1 side with another 3D point displaced 15..40 sigma in image 1.
    """
    s = 1.0 if fix_scale else float(scale)
    axis = rng.normal(size=3)
    R_21 = so3_exp(axis / np.linalg.norm(axis) * np.deg2rad(rng.uniform(5.0, 15.0)))
    direction = rng.normal(size=3)
    t_21 = direction / np.linalg.norm(direction) * rng.uniform(0.3, 1.0)
    T_21 = np.eye(4)
    T_21[:3, :3], T_21[:3, 3] = R_21, t_21
    cand = 4 * n_matches
    x1 = _backproject(_random_pixels(rng, cand), rng.uniform(2.0, 8.0, cand), INTRINSICS)
    uv2c, z2c = project(T_21, x1, INTRINSICS)
    keep = np.flatnonzero(_in_image(uv2c, z2c))
    if len(keep) < n_matches:
        raise ValueError(f"only {len(keep)} candidate points are seen by both keyframes; need {n_matches}")
    x1 = x1[keep[:n_matches]]
    level1 = _random_levels(rng, n_matches)
    level2 = _random_levels(rng, n_matches)
    outlier = _planted(rng, n_matches, outlier_ratio)
    # Wrong matches: keyframe 2's side is another point y, seen in image 1 far from x's pixel, same depth.
    y1 = x1.copy()
    idx = np.flatnonzero(outlier)
    for i in idx:
        for _ in range(100):
            uv_x, _z = project(np.eye(4), x1[i : i + 1], INTRINSICS)
            uv_y = uv_x + _outlier_offsets(rng, _sigma(level1[i : i + 1]) * max(noise_px, 1.0))
            cand_y = _backproject(uv_y, x1[i : i + 1, 2], INTRINSICS)
            if cand_y[0, 2] > 0.1 and project(T_21, cand_y, INTRINSICS)[1][0] > 0.1:
                y1[i] = cand_y[0]
                break
    uv1 = (
        project(np.eye(4), x1, INTRINSICS)[0]
        + rng.normal(0.0, 1.0, (n_matches, 2)) * (noise_px * _sigma(level1))[:, None]
    )
    y2 = y1 @ R_21.T + t_21
    uv2 = (
        project(np.eye(4), y2, INTRINSICS)[0]
        + rng.normal(0.0, 1.0, (n_matches, 2)) * (noise_px * _sigma(level2))[:, None]
    )
    S_21 = _sim3_matrix(s, R_21, s * t_21)
    S_12 = np.asarray(np.linalg.inv(S_21), dtype=np.float64)
    D = np.eye(4)
    D[:3, :3] = (1.0 if fix_scale else float(np.exp(rng.normal(0.0, init_log_scale)))) * so3_exp(
        rng.normal(0.0, init_rot_rad, 3)
    )
    D[:3, 3] = rng.normal(0.0, init_trans_m, 3)
    problem = Sim3Problem(
        S_12_init=D @ S_12,
        xyz1_c1=x1,
        xyz2_c2=s * y2,
        uv1_px=uv1,
        uv2_px=uv2,
        level1=level1,
        level2=level2,
        intrinsics1=INTRINSICS.copy(),
        intrinsics2=INTRINSICS.copy(),
        scale_factor=SCALE_FACTOR,
        fix_scale=fix_scale,
    )
    return problem, Sim3Truth(S_12=S_12, outlier=outlier)


# ---- essential graph ----------------------------------------------------------------------------------


def _loop_trajectory(rng: np.random.Generator, n: int, spacing_m: float) -> F64:
    """(n, 4, 4) T_c_w of a forward-looking camera driving a closed, wavy loop of length ~ n * spacing_m."""
    radius = n * spacing_m / (2.0 * np.pi)
    theta = 2.0 * np.pi * np.arange(n) / n
    phase = rng.uniform(0.0, 2.0 * np.pi)
    r = radius * (1.0 + 0.15 * np.sin(3.0 * theta + phase))
    pos = np.stack([r * np.cos(theta), r * np.sin(theta), 1.7 + 0.5 * np.sin(2.0 * theta)], axis=1)
    ahead = np.roll(pos, -1, axis=0)
    out = np.empty((n, 4, 4))
    for k in range(n):
        out[k] = look_at(pos[k], ahead[k])
    return out


def _random_sim3(rng: np.random.Generator, n: int, rot_rad: float, trans_m: float, log_scale: float) -> F64:
    """(n, 4, 4) small random similarities (rotation/translation/log-scale std per axis)."""
    out = np.tile(np.eye(4), (n, 1, 1))
    s = np.exp(rng.normal(0.0, log_scale, n)) if log_scale > 0 else np.ones(n)
    out[:, :3, :3] = s[:, None, None] * so3_exp(rng.normal(0.0, rot_rad, (n, 3)))
    out[:, :3, 3] = rng.normal(0.0, trans_m, (n, 3))
    return out


def make_essential_graph_problem(
    rng: np.random.Generator,
    n_keyframes: int = 1600,
    n_edges: int = 2000,
    use_sim3: bool = True,
    spacing_m: float = 1.0,
    n_loop_edges: int = 1,
    drift_rot_rad: float = 3e-4,
    drift_trans_m: float = 5e-3,
    drift_log_scale: float = 2e-4,
    noise_rot_rad: float = 1e-4,
    noise_trans_m: float = 1e-3,
    noise_log_scale: float = 1e-4,
) -> tuple[EssentialGraphProblem, EssentialGraphTruth]:
    """A long loop (KITTI 09-like with the defaults: 1600 keyframes ~1 m apart, 2000 edges) closed at keyframe 0.

    Edges: the spanning tree (k-1, k), covisibility edges (k, k+d) for d = 2..6 drawn at random, and
    ``n_loop_edges`` loop edges joining the last keyframes to the first (the fixed loop keyframe 0).
    Measurements S_ij = S_i_w S_j_w^-1 of the truth perturbed by the ``noise_*`` stds. The initial guess is
    odometry with accumulated drift: each step's relative pose is perturbed by the ``drift_*`` stds (per axis),
    and in Sim3 mode the scale drifts too (log-scale random walk with a bias of drift_log_scale per keyframe).
    With use_sim3=False the problem is the SE3 variant: no scale anywhere.
    """
    K = n_keyframes
    n_cov = n_edges - (K - 1) - n_loop_edges
    if K < 10 or n_loop_edges < 1 or n_loop_edges > K // 4 or n_cov < 0:
        raise ValueError(
            f"n_keyframes = {K}, n_edges = {n_edges}, n_loop_edges = {n_loop_edges}: expected K >= 10, "
            "1 <= n_loop_edges <= K / 4 and n_edges >= K - 1 + n_loop_edges"
        )
    T_true = _loop_trajectory(rng, K, spacing_m)
    pairs = np.array([(k, k + d) for d in range(2, 7) for k in range(K - d)], dtype=np.int64)
    if n_cov > len(pairs):
        raise ValueError(f"n_edges = {n_edges}: at most {K - 1 + n_loop_edges + len(pairs)} edges fit this generator")
    cov = pairs[np.sort(rng.choice(len(pairs), size=n_cov, replace=False))]
    tree = np.stack([np.arange(K - 1), np.arange(1, K)], axis=1)
    loop = np.stack([K - 1 - np.arange(n_loop_edges), np.zeros(n_loop_edges, dtype=np.int64)], axis=1)
    edges = np.concatenate([tree, cov, loop]).astype(np.int64)
    E = len(edges)
    T_inv = np.linalg.inv(T_true)
    rel = T_true[edges[:, 0]] @ T_inv[edges[:, 1]]
    noise = _random_sim3(rng, E, noise_rot_rad, noise_trans_m, noise_log_scale if use_sim3 else 0.0)
    S_ij = noise @ rel
    # Odometry with drift: init[k] = D_k (T_k T_{k-1}^-1) init[k-1].
    steps = _random_sim3(rng, K, drift_rot_rad, drift_trans_m, drift_log_scale if use_sim3 else 0.0)
    if use_sim3:
        steps[:, :3, :3] *= np.exp(drift_log_scale)  # biased scale drift
    init = np.empty((K, 4, 4))
    init[0] = T_true[0]
    for k in range(1, K):
        init[k] = steps[k] @ (T_true[k] @ T_inv[k - 1]) @ init[k - 1]
    fixed = np.zeros(K, dtype=bool)
    fixed[0] = True
    problem = EssentialGraphProblem(
        S_c_w=init,
        fixed=fixed,
        edge_i=edges[:, 0].copy(),
        edge_j=edges[:, 1].copy(),
        S_ij=S_ij,
        use_sim3=use_sim3,
    )
    loop_edges = np.arange(E - n_loop_edges, E, dtype=np.int64)
    return problem, EssentialGraphTruth(S_c_w=T_true, loop_edges=loop_edges)


# ---- error measures -----------------------------------------------------------------------------------


def pose_errors(T_est: F64, T_true: F64) -> tuple[F64, F64]:
    """Rotation (rad) and camera-centre (m) errors of (..., 4, 4) rigid T_c_w estimates against the truth."""
    R_err = np.swapaxes(T_est[..., :3, :3], -1, -2) @ T_true[..., :3, :3]
    cos = np.clip((np.trace(R_err, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    c_est = -np.einsum("...ji,...j->...i", T_est[..., :3, :3], T_est[..., :3, 3])
    c_true = -np.einsum("...ji,...j->...i", T_true[..., :3, :3], T_true[..., :3, 3])
    return np.arccos(cos), np.linalg.norm(c_est - c_true, axis=-1)


def sim3_errors(S_est: F64, S_true: F64) -> tuple[F64, F64, F64]:
    """Rotation (rad), camera-centre (m) and |log scale| errors of (..., 4, 4) Sim3 S_c_w against the truth.

    The camera centre of S = [[s R, t], [0, 1]] is -R^T t / s (the point S maps to the origin).
    """
    s_est = np.cbrt(np.linalg.det(S_est[..., :3, :3]))
    s_true = np.cbrt(np.linalg.det(S_true[..., :3, :3]))
    R_est = S_est[..., :3, :3] / s_est[..., None, None]
    R_true = S_true[..., :3, :3] / s_true[..., None, None]
    cos = np.clip((np.trace(np.swapaxes(R_est, -1, -2) @ R_true, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    c_est = -np.einsum("...ji,...j->...i", R_est, S_est[..., :3, 3]) / s_est[..., None]
    c_true = -np.einsum("...ji,...j->...i", R_true, S_true[..., :3, 3]) / s_true[..., None]
    return np.arccos(cos), np.linalg.norm(c_est - c_true, axis=-1), np.abs(np.log(s_est / s_true))
