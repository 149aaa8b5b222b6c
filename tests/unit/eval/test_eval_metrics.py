"""ATE/RPE on synthetic trajectories with known answers."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slamkit.errors import ConfigError, EvaluationError
from slamkit.eval.metrics import apply_sim3, compute_ate, compute_rpe
from slamkit.sensors import Trajectory

MakeTrajectory = Callable[..., Trajectory]  # the make_trajectory fixture (conftest.py)


def _sim3(s: float, rotvec: list[float], t: list[float]) -> np.ndarray:
    S = np.eye(4)
    S[:3, :3] = s * Rotation.from_rotvec(rotvec).as_matrix()
    S[:3, 3] = t
    return S


def _with_positions(traj: Trajectory, xyz: np.ndarray, t_s: np.ndarray | None = None) -> Trajectory:
    T = traj.T_w_c.copy()
    T[:, :3, 3] = xyz
    return Trajectory(traj.t_s.copy() if t_s is None else t_s, T)


def test_apply_sim3_moves_centres_and_keeps_rotations(make_trajectory: MakeTrajectory) -> None:
    traj = make_trajectory(n=10)
    S = _sim3(2.5, [0.1, -0.4, 0.7], [1.0, -2.0, 0.5])
    out = apply_sim3(S, traj)
    np.testing.assert_allclose(out.positions_m, traj.positions_m @ S[:3, :3].T + S[:3, 3], atol=1e-12)
    R = out.T_w_c[:, :3, :3]
    np.testing.assert_allclose(np.einsum("nji,njk->nik", R, R), np.tile(np.eye(3), (10, 1, 1)), atol=1e-12)


def test_sim3_transformed_copy_has_zero_ate_and_recovers_scale(make_trajectory: MakeTrajectory) -> None:
    gt = make_trajectory(n=60, seed=4)
    S_est_gt = _sim3(2.5, [0.3, -0.2, 1.1], [4.0, -1.0, 2.0])
    est = apply_sim3(S_est_gt, gt)
    gt_before, est_before = gt.T_w_c.copy(), est.T_w_c.copy()

    ate = compute_ate(gt, est, align="sim3")
    assert ate.matched_poses == 60
    assert ate.rmse_m < 1e-9 and ate.max_m < 1e-9
    assert ate.scale == pytest.approx(1.0 / 2.5, rel=1e-12)
    # The alignment maps the estimate back into the ground-truth world: S_gt_est = inverse(S_est_gt).
    np.testing.assert_allclose(ate.alignment @ S_est_gt, np.eye(4), atol=1e-9)
    np.testing.assert_allclose(ate.est_aligned.positions_m, gt.positions_m, atol=1e-9)
    # The caller's trajectories are not touched by evo's in-place alignment.
    np.testing.assert_array_equal(gt.T_w_c, gt_before)
    np.testing.assert_array_equal(est.T_w_c, est_before)

    # Without the scale the same pair cannot be aligned.
    assert compute_ate(gt, est, align="se3").rmse_m > 0.5


def test_se3_transformed_copy_has_zero_ate_with_se3(make_trajectory: MakeTrajectory) -> None:
    gt = make_trajectory(n=40, seed=5)
    est = apply_sim3(_sim3(1.0, [-0.5, 0.2, 0.3], [0.0, 3.0, -1.0]), gt)
    ate = compute_ate(gt, est, align="se3")
    assert ate.rmse_m < 1e-9
    assert ate.scale == 1.0
    assert compute_ate(gt, est, align="none").rmse_m > 1.0


def test_known_offset_gives_known_ate_without_alignment(make_trajectory: MakeTrajectory) -> None:
    gt = make_trajectory(n=30, seed=6)
    est = _with_positions(gt, gt.positions_m + np.array([0.3, 0.0, 0.4]))
    ate = compute_ate(gt, est, align="none")
    np.testing.assert_allclose(ate.errors_m, 0.5, atol=1e-12)
    for v in (ate.rmse_m, ate.mean_m, ate.median_m, ate.max_m, ate.min_m):
        assert v == pytest.approx(0.5, abs=1e-12)
    assert ate.std_m == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_array_equal(ate.alignment, np.eye(4))
    # A constant offset is a rigid motion: SE3 alignment removes it.
    assert compute_ate(gt, est, align="se3").rmse_m < 1e-9


def test_known_per_pose_errors_give_known_statistics(make_trajectory: MakeTrajectory) -> None:
    gt = make_trajectory(n=4, seed=7)
    err = np.array([0.0, 1.0, 2.0, 3.0])
    est = _with_positions(gt, gt.positions_m + err[:, None] * np.array([0.0, 0.0, 1.0]))
    ate = compute_ate(gt, est, align="none")
    np.testing.assert_allclose(ate.errors_m, err, atol=1e-12)
    assert ate.rmse_m == pytest.approx(np.sqrt(14.0 / 4.0), abs=1e-12)
    assert ate.mean_m == pytest.approx(1.5, abs=1e-12)
    assert ate.median_m == pytest.approx(1.5, abs=1e-12)
    assert (ate.max_m, ate.min_m) == (pytest.approx(3.0), pytest.approx(0.0))


def test_association_by_timestamp_within_max_diff(make_trajectory: MakeTrajectory) -> None:
    gt = make_trajectory(n=50, seed=8, dt_s=0.1)
    # Every other pose, stamped 4 ms late: matched to the right gt pose within 0.01 s.
    est = Trajectory(gt.t_s[::2] + 0.004, gt.T_w_c[::2].copy())
    ate = compute_ate(gt, est, align="none")
    assert ate.matched_poses == 25
    np.testing.assert_allclose(ate.t_s, gt.t_s[::2])
    assert ate.rmse_m < 1e-12
    # Tightening max_diff below the lag leaves nothing to match.
    with pytest.raises(EvaluationError, match=r"only 0 poses matched by time \(max time difference 0.001 s\)"):
        compute_ate(gt, est, max_diff_s=0.001)


def test_too_few_matches_reports_counts_and_time_ranges(make_trajectory: MakeTrajectory) -> None:
    gt = make_trajectory(n=20, seed=9, t0_s=100.0, dt_s=0.1)
    est = Trajectory(np.array([100.0, 100.1, 500.0]), gt.T_w_c[:3].copy())
    with pytest.raises(EvaluationError) as info:
        compute_ate(gt, est, gt_name="gt.txt", est_name="est.txt")
    msg = str(info.value)
    assert "only 2 poses matched" in msg and "need at least 3" in msg
    assert "gt.txt has 20 poses over t = [100.000000, 101.900000] s" in msg
    assert "est.txt has 3 poses over t = [100.000000, 500.000000] s" in msg


def test_index_association_needs_equal_lengths(make_trajectory: MakeTrajectory) -> None:
    gt = make_trajectory(n=20, seed=10, t0_s=0.0, dt_s=1.0)
    est = Trajectory(np.arange(20.0) * 7.0, gt.T_w_c.copy())  # timestamps unrelated: index decides
    assert compute_ate(gt, est, association="index").rmse_m < 1e-12
    with pytest.raises(EvaluationError, match="ground truth has 20 poses, estimate has 19"):
        compute_ate(gt, Trajectory(est.t_s[:19], est.T_w_c[:19]), association="index")


def test_degenerate_estimate_is_a_clear_error(make_trajectory: MakeTrajectory) -> None:
    gt = make_trajectory(n=10, seed=11)
    est = _with_positions(gt, np.zeros((10, 3)))
    with pytest.raises(EvaluationError, match="sim3 alignment of estimate to ground truth failed on 10"):
        compute_ate(gt, est, align="sim3")


def test_bad_parameters_are_config_errors(make_trajectory: MakeTrajectory) -> None:
    gt = make_trajectory(n=10)
    with pytest.raises(ConfigError, match=r"align='sim2' is not valid; expected one of \['sim3', 'se3', 'none'\]"):
        compute_ate(gt, gt, align="sim2")
    with pytest.raises(ConfigError, match="max_diff_s=-1"):
        compute_ate(gt, gt, max_diff_s=-1)
    with pytest.raises(ConfigError, match=r"delta=1\.5 is not valid for delta_unit='frames'"):
        compute_rpe(gt, gt, delta=1.5)
    with pytest.raises(ConfigError, match="delta_unit='s'"):
        compute_rpe(gt, gt, delta_unit="s")
    with pytest.raises(EvaluationError, match="estimate trajectory is empty"):
        compute_ate(gt, Trajectory(np.zeros(0), np.zeros((0, 4, 4))))


def test_rpe_of_scaled_copy_is_step_length_unaligned_and_zero_with_sim3(make_trajectory: MakeTrajectory) -> None:
    gt = make_trajectory(n=30, seed=12)
    est = _with_positions(gt, 2.0 * gt.positions_m)
    # Relative translation of the estimate is twice the true one: the error is one step length.
    rpe = compute_rpe(gt, est, align="none")
    steps = np.linalg.norm(np.diff(gt.positions_m, axis=0), axis=1)
    assert rpe.num_pairs == 29
    np.testing.assert_allclose(rpe.errors_m, steps, atol=1e-12)
    assert rpe.rmse_m == pytest.approx(float(np.sqrt(np.mean(steps**2))), abs=1e-12)
    np.testing.assert_allclose(rpe.errors_deg, 0.0, atol=1e-9)
    aligned = compute_rpe(gt, est, align="sim3")
    assert aligned.scale == pytest.approx(0.5, rel=1e-12)
    assert aligned.rmse_m < 1e-9
    # delta=3 frames -> pairs (0,3), (3,6), ... as evo's consecutive pairs.
    assert compute_rpe(gt, est, delta=3, align="none").num_pairs == 9


def test_rpe_rotation_error_of_one_perturbed_pose(make_trajectory: MakeTrajectory) -> None:
    gt = make_trajectory(n=12, seed=13)
    T = gt.T_w_c.copy()
    T[5, :3, :3] = T[5, :3, :3] @ Rotation.from_rotvec([0.0, 0.0, np.deg2rad(2.0)]).as_matrix()
    rpe = compute_rpe(gt, Trajectory(gt.t_s.copy(), T), align="none")
    expected = np.zeros(11)
    expected[[4, 5]] = 2.0  # pairs (4,5) and (5,6)
    np.testing.assert_allclose(rpe.errors_deg, expected, atol=1e-9)
    assert rpe.rot_max_deg == pytest.approx(2.0, abs=1e-9)
