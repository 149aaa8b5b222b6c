"""Motion-only BA of a two-camera rig (non-rectified stereo; ORB-SLAM3 EdgeSE3ProjectXYZOnlyPoseToBody): the second
camera's observations are residuals of their own through its model at T_c2_c1 T_c_w. With a fisheye pair diverging
by 15 degrees the body pose is recovered from either camera alone or both, planted outliers of either camera are
flagged, and a one-camera problem gives the same answer bit for bit with or without the new fields."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from slamkit.errors import ProblemError
from slamkit.geometry.camera import KannalaBrandtCamera, PinholeCamera
from slamkit.geometry.so3 import so3_exp
from slamkit.optim.costs import pose_cost
from slamkit.optim.synthetic import make_pose_problem, pose_errors
from slamkit.optim.validation import validate_pose_problem
from slamkit.pipeline.pose_optimization import optimize_pose
from slamkit.problems import PoseOnlyProblem

CAM1 = KannalaBrandtCamera(640, 480, 280.0, 280.0, 320.0, 240.0, k=[-0.01, 0.05, -0.08, 0.04])
CAM2 = KannalaBrandtCamera(640, 480, 285.0, 283.0, 318.0, 244.0, k=[-0.012, 0.04, -0.07, 0.03])


def _T(rotvec: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = so3_exp(rotvec)
    T[:3, 3] = t
    return T


# camera 2 10 cm to the right of camera 1, turned 15 degrees outwards: T_c1_c2; the problem takes T_c2_c1
T_C1_C2 = _T(np.array([0.0, np.radians(15.0), 0.0]), np.array([0.10, 0.0, 0.0]))
T_C2_C1 = np.linalg.inv(T_C1_C2)


def _problem(
    seed: int, which: str, outliers: float = 0.0, cam2: KannalaBrandtCamera | PinholeCamera = CAM2
) -> tuple[PoseOnlyProblem, np.ndarray, np.ndarray]:
    """Points around the rig seen by camera 1 and / or camera 2 ('1', '2' or 'both') -> (problem, true T_c_w).
    Planted outliers (a fraction of each camera's observations) are moved by 20-40 px."""
    rng = np.random.default_rng(seed)
    T_true = _T(rng.normal(0, 0.3, 3), rng.normal(0, 1.0, 3))
    T_w_c = np.linalg.inv(T_true)
    p_c = rng.uniform([-4, -2, 1.0], [4, 2, 5.0], (500, 3))
    xyz_w = p_c @ T_w_c[:3, :3].T + T_w_c[:3, 3]
    rows: list[tuple[int, int, np.ndarray]] = []
    for cam_i, cam, T in ((0, CAM1, T_true), (1, cam2, T_C2_C1 @ T_true)):
        if (which == "1" and cam_i == 1) or (which == "2" and cam_i == 0):
            continue
        pc = xyz_w @ T[:3, :3].T + T[:3, 3]
        uv, ok = cam.project_image(pc)
        ok &= cam.in_image(uv, 5)
        for j in np.flatnonzero(ok):
            rows.append((j, cam_i, uv[j] + rng.normal(0, 0.5, 2)))
    j = np.array([r[0] for r in rows])
    cams = np.array([r[1] for r in rows], np.int64)
    uv = np.array([r[2] for r in rows])
    bad = rng.random(len(rows)) < outliers
    uv[bad] += rng.uniform(20, 40, (bad.sum(), 2)) * rng.choice([-1, 1], (bad.sum(), 2))
    init = _T(np.array([0.03, -0.02, 0.02]), np.array([0.05, -0.04, 0.06])) @ T_true
    c2 = cam2
    problem = PoseOnlyProblem(
        T_c_w_init=init,
        xyz_w=xyz_w[j],
        uv_px=uv,
        u_right_px=np.full(len(rows), np.nan),
        level=rng.integers(0, 3, len(rows)),
        intrinsics=np.array([CAM1.fx, CAM1.fy, CAM1.cx, CAM1.cy]),
        camera_model="kannala_brandt",
        distortion=np.asarray(CAM1.k),
        camera_index=cams,
        T_c2_c1=T_C2_C1,
        intrinsics2=np.array([c2.fx, c2.fy, c2.cx, c2.cy]),
        camera_model2=c2.model,
        distortion2=np.asarray(c2.dist) if c2.model == "kannala_brandt" else None,
    )
    return problem, T_true, bad


@pytest.mark.parametrize("which", ["1", "2", "both"])
def test_recovers_the_body_pose_from_either_camera(which: str) -> None:
    problem, T_true, _ = _problem(3, which)
    assert len(problem.xyz_w) > 100
    result = optimize_pose(problem)
    rot, pos = pose_errors(result.T_c_w, T_true)
    assert rot < 2e-3 and pos < 5e-3
    assert result.inliers.mean() > 0.95
    if which == "2":
        # the same observations read as camera 1's: the extrinsic is what makes them agree
        wrong = optimize_pose(replace(problem, camera_index=np.zeros(len(problem.xyz_w), np.int64)))
        assert pose_errors(wrong.T_c_w, T_true)[1] > 0.05


def test_second_pinhole_camera() -> None:
    cam2 = PinholeCamera(640, 480, 450.0, 450.0, 320.0, 240.0)
    problem, T_true, _ = _problem(4, "both", cam2=cam2)
    assert (problem.camera_index == 1).sum() > 50  # type: ignore[union-attr]
    rot, pos = pose_errors(optimize_pose(problem).T_c_w, T_true)
    assert rot < 2e-3 and pos < 5e-3


def test_outliers_of_both_cameras_are_flagged() -> None:
    problem, T_true, bad = _problem(5, "both", outliers=0.15)
    result = optimize_pose(problem)
    rot, pos = pose_errors(result.T_c_w, T_true)
    assert rot < 3e-3 and pos < 1e-2
    cams = problem.camera_index
    assert cams is not None
    for c in (0, 1):
        assert (bad & (cams == c)).sum() > 5
        assert not (result.inliers & bad & (cams == c)).any()
        assert (result.inliers & ~bad & (cams == c)).sum() > 0.9 * (~bad & (cams == c)).sum()


def test_one_camera_problem_is_unchanged_bit_for_bit() -> None:
    problem, _ = make_pose_problem(np.random.default_rng(7), n_points=250, outlier_ratio=0.1)
    a = optimize_pose(problem)
    b = optimize_pose(replace(problem, camera_index=np.zeros(len(problem.xyz_w), np.int64)))
    assert np.array_equal(a.T_c_w, b.T_c_w) and np.array_equal(a.inliers, b.inliers)
    assert a.cost_final == b.cost_final and a.iterations == b.iterations


def test_second_camera_observation_without_the_rig_is_refused() -> None:
    problem, _, _ = _problem(6, "both")
    with pytest.raises(ValueError, match="T_c2_c1"):
        optimize_pose(replace(problem, T_c2_c1=None))


def test_cost_agrees_with_the_shared_cost_and_backends_refuse_the_rig() -> None:
    problem, _, _ = _problem(8, "both", outliers=0.1)
    result = optimize_pose(problem)
    assert result.cost_final == pytest.approx(pose_cost(problem, result.T_c_w, result.inliers), rel=1e-9)
    assert result.cost_initial == pytest.approx(pose_cost(problem, problem.T_c_w_init), rel=1e-9)
    validate_pose_problem(problem, supports_rig=True)
    with pytest.raises(ProblemError, match="second-camera observations"):
        validate_pose_problem(problem, backend="scipy")


@pytest.mark.parametrize(
    "cam2", [CAM2, PinholeCamera(640, 480, 450.0, 450.0, 320.0, 240.0)], ids=["fisheye", "pinhole"]
)
def test_gtsam_backend_agrees(cam2: KannalaBrandtCamera | PinholeCamera) -> None:
    gtsam_backend = pytest.importorskip("slamkit_gtsam.backend")
    problem, T_true, bad = _problem(9, "both", outliers=0.1, cam2=cam2)
    ours = optimize_pose(problem)
    ref = gtsam_backend.GtsamOptimizer().optimize_pose(problem)
    rot, pos = pose_errors(ref.T_c_w, T_true)
    assert rot < 3e-3 and pos < 1e-2
    assert pose_errors(ref.T_c_w, ours.T_c_w)[1] < 1e-4
    assert np.array_equal(ref.inliers, ours.inliers)
    assert not (ref.inliers & bad).any()


@pytest.mark.parametrize(
    "cam2", [CAM2, PinholeCamera(640, 480, 450.0, 450.0, 320.0, 240.0)], ids=["fisheye", "pinhole"]
)
def test_scipy_backend_matches_the_compiled_kernel(cam2: KannalaBrandtCamera | PinholeCamera) -> None:
    from slamkit_scipy.optimizer import ScipyOptimizer

    problem, _, _ = _problem(10, "both", outliers=0.1, cam2=cam2)
    ours = optimize_pose(problem)
    ref = ScipyOptimizer().optimize_pose(problem)
    np.testing.assert_allclose(ours.T_c_w, ref.T_c_w, atol=1e-9)
    np.testing.assert_array_equal(ours.inliers, ref.inliers)
    assert ours.cost_final == pytest.approx(ref.cost_final, rel=1e-9)
