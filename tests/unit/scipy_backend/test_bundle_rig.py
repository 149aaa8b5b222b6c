"""Bundle adjustment with a two-camera rig (non-rectified stereo; ORB-SLAM3 EdgeSE3ProjectXYZToBody), SciPy and GTSAM
backends: keyframes of a fisheye pair diverging by 15 degrees, points seen by camera 1, camera 2 or both; from
perturbed poses and points both backends return the true ones (metric: the rig fixes the scale) and flag the planted
outliers of either camera; a one-camera problem is unchanged bit for bit by an all-zero camera_index."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from slamkit_scipy.optimizer import ScipyOptimizer

from slamkit.geometry.camera import KannalaBrandtCamera, PinholeCamera
from slamkit.geometry.so3 import so3_exp
from slamkit.optim.synthetic import pose_errors
from slamkit.problems import BundleProblem

CAM1 = KannalaBrandtCamera(640, 480, 280.0, 280.0, 320.0, 240.0, k=[-0.01, 0.05, -0.08, 0.04])
CAM2 = KannalaBrandtCamera(640, 480, 285.0, 283.0, 318.0, 244.0, k=[-0.012, 0.04, -0.07, 0.03])


def _T(rotvec: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = so3_exp(rotvec)
    T[:3, 3] = t
    return T


T_C2_C1 = np.linalg.inv(_T(np.array([0.0, np.radians(15.0), 0.0]), np.array([0.10, 0.0, 0.0])))


def _problem(
    seed: int, outliers: float = 0.0, cam2: KannalaBrandtCamera | PinholeCamera = CAM2
) -> tuple[BundleProblem, np.ndarray, np.ndarray, np.ndarray]:
    """4 keyframes 20 cm apart looking at points 1-5 m away -> (problem from perturbed estimates, true T_c_w (K, 4, 4),
    true xyz_w (M, 3), planted outliers (E,))."""
    rng = np.random.default_rng(seed)
    K = 4
    T_true = np.stack([_T(rng.normal(0, 0.05, 3), np.array([-0.2 * k, 0.0, 0.0])) for k in range(K)])
    xyz = rng.uniform([-4, -2, 1.0], [4, 2, 5.0], (300, 3))
    obs: list[tuple[int, int, int, np.ndarray]] = []
    for k in range(K):
        for ci, cam, T in ((0, CAM1, T_true[k]), (1, cam2, T_C2_C1 @ T_true[k])):
            pc = xyz @ T[:3, :3].T + T[:3, 3]
            uv, ok = cam.project_image(pc)
            ok &= cam.in_image(uv, 5)
            for j in np.flatnonzero(ok):
                obs.append((k, j, ci, uv[j] + rng.normal(0, 0.5, 2)))
    E = len(obs)
    uv = np.array([o[3] for o in obs])
    bad = rng.random(E) < outliers
    uv[bad] += rng.uniform(15, 30, (bad.sum(), 2)) * rng.choice([-1, 1], (bad.sum(), 2))
    T_init = T_true.copy()
    for k in range(1, K):
        T_init[k] = _T(rng.normal(0, 0.01, 3), rng.normal(0, 0.02, 3)) @ T_true[k]
    problem = BundleProblem(
        T_c_w=T_init,
        pose_fixed=np.array([True] + [False] * (K - 1)),
        intrinsics=np.tile([CAM1.fx, CAM1.fy, CAM1.cx, CAM1.cy], (K, 1)),
        bf=np.zeros(K),
        xyz_w=xyz + rng.normal(0, 0.03, xyz.shape),
        point_fixed=np.bincount([o[1] for o in obs], minlength=len(xyz)) == 0,  # points nobody sees stay out
        obs_pose=np.array([o[0] for o in obs], np.int64),
        obs_point=np.array([o[1] for o in obs], np.int64),
        uv_px=uv,
        u_right_px=np.full(E, np.nan),
        level=rng.integers(0, 3, E),
        camera_model="kannala_brandt",
        distortion=np.tile(CAM1.k, (K, 1)),
        camera_index=np.array([o[2] for o in obs], np.int64),
        T_c2_c1=np.tile(T_C2_C1, (K, 1, 1)),
        intrinsics2=np.tile([cam2.fx, cam2.fy, cam2.cx, cam2.cy], (K, 1)),
        camera_model2=cam2.model,
        distortion2=np.tile(cam2.dist, (K, 1)) if cam2.model == "kannala_brandt" else None,
        iterations_first=10,
        iterations_second=10,
    )
    return problem, T_true, xyz, bad


def _backends() -> list[object]:
    out: list[object] = [ScipyOptimizer()]
    try:
        from slamkit_gtsam.backend import GtsamOptimizer

        out.append(GtsamOptimizer())
    except ImportError:  # pragma: no cover - gtsam is optional
        pass
    return out


@pytest.mark.parametrize(
    "cam2", [CAM2, PinholeCamera(640, 480, 450.0, 450.0, 320.0, 240.0)], ids=["fisheye", "pinhole"]
)
def test_both_backends_recover_poses_points_and_outliers(cam2: KannalaBrandtCamera | PinholeCamera) -> None:
    problem, T_true, xyz, bad = _problem(1, outliers=0.05, cam2=cam2)
    second = problem.camera_index == 1  # type: ignore[operator]
    assert second.sum() > 200 and (~second).sum() > 200
    points_of_both = np.intersect1d(problem.obs_point[second], problem.obs_point[~second])
    assert points_of_both.size > 50
    results = []
    for backend in _backends():
        res = backend.bundle_adjust(problem)  # type: ignore[attr-defined]
        rot, pos = pose_errors(res.T_c_w, T_true)
        assert rot.max() < 2e-3 and pos.max() < 5e-3
        err = np.linalg.norm(res.xyz_w - xyz, axis=1)[~problem.point_fixed]
        assert np.median(err) < 0.08  # depth noise ~ z^2 / (baseline fx) x 0.5 px: a few cm at 3-5 m
        for c in (False, True):
            sel = second == c
            # a planted outlier on a point with few observations can be absorbed by moving the point
            assert (~res.outlier & bad & sel).sum() <= 0.15 * (bad & sel).sum()
            assert (res.outlier & ~bad & sel).sum() < 0.05 * (~bad & sel).sum()
        results.append(res)
    if len(results) == 2:
        assert pose_errors(results[0].T_c_w, results[1].T_c_w)[1].max() < 1e-4
        # LM stops differ; a point left with few inlier observations may go its own way in each backend
        assert np.median(np.linalg.norm(results[0].xyz_w - results[1].xyz_w, axis=1)) < 1e-3
        assert (results[0].outlier != results[1].outlier).sum() <= 0.01 * len(bad)  # gate-borderline ones


def test_one_camera_problem_unchanged_by_a_zero_camera_index() -> None:
    problem, _, _, _ = _problem(2, outliers=0.05)
    one = replace(
        problem,
        obs_pose=problem.obs_pose[problem.camera_index == 0],  # type: ignore[operator]
        obs_point=problem.obs_point[problem.camera_index == 0],  # type: ignore[operator]
        uv_px=problem.uv_px[problem.camera_index == 0],  # type: ignore[operator]
        u_right_px=problem.u_right_px[problem.camera_index == 0],  # type: ignore[operator]
        level=problem.level[problem.camera_index == 0],  # type: ignore[operator]
        camera_index=None,
        T_c2_c1=None,
        intrinsics2=None,
        camera_model2="pinhole",
        distortion2=None,
    )
    # points seen only by camera 2 are left without observations: fix them so the problem stays valid
    seen = np.bincount(one.obs_point, minlength=len(one.xyz_w)) > 0
    one = replace(one, point_fixed=~seen)
    a = ScipyOptimizer().bundle_adjust(one)
    b = ScipyOptimizer().bundle_adjust(replace(one, camera_index=np.zeros(len(one.obs_pose), np.int64)))
    assert np.array_equal(a.T_c_w, b.T_c_w) and np.array_equal(a.xyz_w, b.xyz_w)
    assert np.array_equal(a.outlier, b.outlier) and a.cost_final == b.cost_final


def test_rig_gradient_matches_finite_differences() -> None:
    """d cost / d (pose twist, point) of the rig kernels = 2 g (no robust kernel), by central differences."""
    from slamkit_scipy.bundle import BAState, BundleSolver, _Stage, rig_terms
    from slamkit_scipy.lie import se3_exp_batch
    from slamkit_scipy.reprojection import make_observations
    from slamkit_scipy.robust import inv_sigma2

    problem, _, _, _ = _problem(3, cam2=PinholeCamera(640, 480, 450.0, 450.0, 320.0, 240.0))
    problem = replace(problem, robust=False)
    obs = make_observations(
        problem.uv_px,
        problem.u_right_px,
        problem.intrinsics[problem.obs_pose],
        problem.bf[problem.obs_pose],
        inv_sigma2(problem.level, problem.scale_factor),
        problem.chi2_mono,
        problem.chi2_stereo,
        np.asarray(problem.distortion)[problem.obs_pose],
    )
    rig = rig_terms(problem, obs)
    assert rig is not None
    solver = BundleSolver(_Stage(problem, obs, np.ones(len(problem.obs_pose), bool), False, rig), 3000)
    state = BAState(problem.T_c_w.copy(), problem.xyz_w.copy())
    _, g, _, _ = solver.linearize(state)
    st = solver.st
    h = 1e-6
    for a in range(6):  # first free pose
        d = np.zeros(6)
        d[a] = h
        plus = state.T_c_w.copy()
        minus = state.T_c_w.copy()
        k = st.free_poses[0]
        plus[k] = se3_exp_batch(d[None])[0] @ plus[k]
        minus[k] = se3_exp_batch(-d[None])[0] @ minus[k]
        num = (solver.cost(BAState(plus, state.xyz_w)) - solver.cost(BAState(minus, state.xyz_w))) / (2 * h)
        assert num == pytest.approx(2 * g[a], rel=1e-4, abs=1e-3)
    q = int(np.flatnonzero(np.isin(st.free_points, problem.obs_point[problem.camera_index == 1]))[0])  # type: ignore[operator]
    j = st.free_points[q]
    for a in range(3):
        plus = state.xyz_w.copy()
        minus = state.xyz_w.copy()
        plus[j, a] += h
        minus[j, a] -= h
        num = (solver.cost(BAState(state.T_c_w, plus)) - solver.cost(BAState(state.T_c_w, minus))) / (2 * h)
        assert num == pytest.approx(2 * g[6 * st.nc + 3 * q + a], rel=1e-4, abs=1e-3)
