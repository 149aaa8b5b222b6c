"""Absolute and relative trajectory error (ATE/RPE), computed by evo so the numbers agree with evo_ape/evo_rpe.

Pipeline, as ``evo_ape tum GT EST`` does it: associate poses by timestamp (evo's ``sync.associate_trajectories``,
nearest stamp within ``max_diff_s``; or by index for KITTI files without times), align the estimate to the ground
truth with Umeyama's method on the positions (``se3``, ``sim3`` with scale, or ``none``), then take the statistics
of evo's APE/RPE translation errors.

Alignment is reported as a Sim3 ``S_gt_est`` = ``[[s R, t], [0, 1]]`` mapping estimate-world points into the
ground-truth world (``x' = s R x + t``, docs/conventions.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from evo import EvoException
from evo.core import lie_algebra, sync
from evo.core import metrics as evo_metrics
from evo.core.trajectory import PoseTrajectory3D
from evo.core.units import Unit

from slamkit.errors import ConfigError, EvaluationError
from slamkit.sensors import F64, Trajectory

Align = Literal["se3", "sim3", "none"]
Association = Literal["time", "index"]
DeltaUnit = Literal["frames", "m", "deg", "rad"]

ALIGN_MODES: tuple[str, ...] = ("sim3", "se3", "none")
ASSOCIATIONS: tuple[str, ...] = ("time", "index")
_DELTA_UNITS: dict[str, Unit] = {
    "frames": Unit.frames,
    "m": Unit.meters,
    "deg": Unit.degrees,
    "rad": Unit.radians,
}
# Fewer matched poses cannot constrain a 7-DoF Sim3 (and give meaningless statistics).
MIN_MATCHED_POSES = 3


@dataclass(frozen=True, eq=False)
class AteResult:
    """Absolute trajectory error: translation error after alignment, metres.

    errors_m: (M,) per matched pose, |p_gt - (s R p_est + t)| m.
    t_s: (M,) s, timestamps of the matched ground-truth poses.
    alignment: (4, 4) Sim3 S_gt_est = [[s R, t], [0, 1]] applied to the estimate (identity for "none").
    gt_matched / est_aligned: the matched poses, the estimate after alignment (same length M).
    """

    rmse_m: float
    mean_m: float
    median_m: float
    max_m: float
    min_m: float
    std_m: float
    matched_poses: int
    align: str
    scale: float
    alignment: F64
    errors_m: F64
    t_s: F64
    gt_matched: Trajectory
    est_aligned: Trajectory


@dataclass(frozen=True, eq=False)
class RpeResult:
    """Relative pose error over pose pairs ``delta`` apart (evo's RPE, consecutive pairs by default).

    Translation part in metres, rotation angle in degrees; errors_m / errors_deg: (P,) per pair.
    """

    rmse_m: float
    mean_m: float
    median_m: float
    max_m: float
    min_m: float
    std_m: float
    rot_rmse_deg: float
    rot_mean_deg: float
    rot_median_deg: float
    rot_max_deg: float
    num_pairs: int
    delta: float
    delta_unit: str
    matched_poses: int
    align: str
    scale: float
    alignment: F64
    errors_m: F64
    errors_deg: F64


def _to_evo(traj: Trajectory, name: str) -> PoseTrajectory3D:
    # Copies: evo aligns in place and must not touch the caller's arrays.
    return PoseTrajectory3D(poses_se3=list(traj.T_w_c.copy()), timestamps=traj.t_s.copy(), name=name)


def _from_evo(traj: PoseTrajectory3D) -> Trajectory:
    return Trajectory(np.asarray(traj.timestamps, dtype=np.float64), np.asarray(traj.poses_se3))


def _span(traj: Trajectory) -> str:
    return f"{len(traj)} poses over t = [{traj.t_s[0]:.6f}, {traj.t_s[-1]:.6f}] s"


def _check_choice(value: str, parameter: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ConfigError(f"{parameter}={value!r} is not valid; expected one of {list(choices)}")


def _associate(
    gt: Trajectory,
    est: Trajectory,
    max_diff_s: float,
    association: str,
    gt_name: str,
    est_name: str,
) -> tuple[PoseTrajectory3D, PoseTrajectory3D]:
    """Matched (gt, est) evo trajectories of equal length, at least MIN_MATCHED_POSES."""
    _check_choice(association, "association", ASSOCIATIONS)
    if not (np.isfinite(max_diff_s) and max_diff_s >= 0):
        raise ConfigError(f"max_diff_s={max_diff_s!r} is not valid; expected a time difference >= 0 s")
    for traj, name in ((gt, gt_name), (est, est_name)):
        if len(traj) == 0:
            raise EvaluationError(f"{name} trajectory is empty; expected at least {MIN_MATCHED_POSES} poses")
        if not (np.isfinite(traj.T_w_c).all() and np.isfinite(traj.t_s).all()):
            raise EvaluationError(f"{name} trajectory has non-finite timestamps or poses")
    gt_e, est_e = _to_evo(gt, gt_name), _to_evo(est, est_name)
    if association == "index":
        if len(gt) != len(est):
            raise EvaluationError(
                f"association by index needs equally long trajectories: {gt_name} has {len(gt)} poses, "
                f"{est_name} has {len(est)}"
            )
        matched = len(gt)
    else:
        try:
            gt_e, est_e = sync.associate_trajectories(gt_e, est_e, max_diff=max_diff_s)
            matched = gt_e.num_poses
        except sync.SyncException:
            matched = 0
    if matched < MIN_MATCHED_POSES:
        raise EvaluationError(
            f"only {matched} poses matched by {association} (max time difference {max_diff_s} s), "
            f"need at least {MIN_MATCHED_POSES}: {gt_name} has {_span(gt)}, {est_name} has {_span(est)}"
        )
    return gt_e, est_e


def _align(gt_e: PoseTrajectory3D, est_e: PoseTrajectory3D, align: str) -> tuple[F64, float]:
    """Align est_e to gt_e in place (as evo_ape -a / -as); return the Sim3 S_gt_est and its scale."""
    _check_choice(align, "align", ALIGN_MODES)
    if align == "none":
        return np.eye(4), 1.0
    try:
        r, t, s = est_e.align(gt_e, correct_scale=(align == "sim3"))
    except EvoException as exc:
        raise EvaluationError(
            f"{align} alignment of {est_e.name} to {gt_e.name} failed on {gt_e.num_poses} matched poses "
            f"({exc}); the matched positions are degenerate (all equal or collinear)"
        ) from exc
    if not (np.isfinite(s) and s > 0):
        raise EvaluationError(f"{align} alignment of {est_e.name} gave scale {s}: its matched positions do not move")
    return np.asarray(lie_algebra.sim3(r, t, s), dtype=np.float64), float(s)


def apply_sim3(S: F64, traj: Trajectory) -> Trajectory:
    """Trajectory with every pose moved by the Sim3 S = [[s R, t], [0, 1]]: centres p' = s R p + t, rotations
    R' = R R_w_c (scale changes positions only, the result is still made of SE3 poses)."""
    s = float(np.cbrt(np.linalg.det(S[:3, :3])))
    if not (np.isfinite(s) and s > 0):
        raise ConfigError(f"S is not a Sim3 (det of its 3x3 block is {np.linalg.det(S[:3, :3])}); expected > 0")
    R = S[:3, :3] / s
    T = traj.T_w_c.copy()
    T[:, :3, :3] = R @ traj.T_w_c[:, :3, :3]
    T[:, :3, 3] = traj.T_w_c[:, :3, 3] @ S[:3, :3].T + S[:3, 3]
    return Trajectory(traj.t_s.copy(), T)


def compute_ate(
    gt: Trajectory,
    est: Trajectory,
    align: Align | str = "sim3",
    max_diff_s: float = 0.01,
    *,
    association: Association | str = "time",
    gt_name: str = "ground truth",
    est_name: str = "estimate",
) -> AteResult:
    """Absolute trajectory error (evo APE, translation part, metres) of ``est`` against ``gt``.

    align: "sim3" (Umeyama with scale, ``evo_ape -as``: monocular), "se3" (``-a``) or "none".
    max_diff_s: largest |t_gt - t_est| s for two poses to be associated (evo's default 0.01 s).
    association: "time" (nearest timestamps) or "index" (pose i with pose i; KITTI files without times).
    Raises EvaluationError when fewer than 3 poses match or the alignment is degenerate.
    """
    gt_e, est_e = _associate(gt, est, max_diff_s, str(association), gt_name, est_name)
    S, scale = _align(gt_e, est_e, str(align))
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((gt_e, est_e))
    return AteResult(
        **_statistics(ape, "_m"),
        matched_poses=int(gt_e.num_poses),
        align=str(align),
        scale=scale,
        alignment=S,
        errors_m=np.asarray(ape.error, dtype=np.float64),
        t_s=np.asarray(gt_e.timestamps, dtype=np.float64),
        gt_matched=_from_evo(gt_e),
        est_aligned=_from_evo(est_e),
    )


def compute_rpe(
    gt: Trajectory,
    est: Trajectory,
    delta: float = 1,
    delta_unit: DeltaUnit | str = "frames",
    align: Align | str = "sim3",
    max_diff_s: float = 0.01,
    *,
    association: Association | str = "time",
    all_pairs: bool = False,
    gt_name: str = "ground truth",
    est_name: str = "estimate",
) -> RpeResult:
    """Relative pose error (evo RPE) of ``est`` against ``gt`` over pairs ``delta`` apart.

    delta_unit: "frames" (matched-pose index steps, integer delta), "m" (travelled distance), "deg" or "rad"
    (rotation); pairs are consecutive unless all_pairs. align/max_diff_s/association as in compute_ate; the
    alignment only matters through its scale (relative poses do not see a rigid motion), as in evo_rpe -as.
    """
    _check_choice(str(delta_unit), "delta_unit", tuple(_DELTA_UNITS))
    if not (np.isfinite(delta) and delta > 0):
        raise ConfigError(f"delta={delta!r} is not valid; expected a positive step")
    if delta_unit == "frames" and float(delta) != int(delta):
        raise ConfigError(f"delta={delta!r} is not valid for delta_unit='frames'; expected an integer")
    gt_e, est_e = _associate(gt, est, max_diff_s, str(association), gt_name, est_name)
    S, scale = _align(gt_e, est_e, str(align))
    unit = _DELTA_UNITS[str(delta_unit)]
    step = int(delta) if unit is Unit.frames else float(delta)
    try:
        trans = evo_metrics.RPE(evo_metrics.PoseRelation.translation_part, step, unit, all_pairs=all_pairs)
        trans.process_data((gt_e, est_e))
        rot = evo_metrics.RPE(evo_metrics.PoseRelation.rotation_angle_deg, step, unit, all_pairs=all_pairs)
        rot.process_data((gt_e, est_e))
    except EvoException as exc:
        raise EvaluationError(
            f"RPE with delta={delta} {delta_unit} over {gt_e.num_poses} matched poses found no pose pairs ({exc})"
        ) from exc
    rot_stats = _statistics(rot, "_deg", prefix="rot_")
    return RpeResult(
        **_statistics(trans, "_m"),
        **{k: v for k, v in rot_stats.items() if k in _RPE_ROTATION_FIELDS},
        num_pairs=len(trans.error),
        delta=float(delta),
        delta_unit=str(delta_unit),
        matched_poses=int(gt_e.num_poses),
        align=str(align),
        scale=scale,
        alignment=S,
        errors_m=np.asarray(trans.error, dtype=np.float64),
        errors_deg=np.asarray(rot.error, dtype=np.float64),
    )


#: The rotation statistics RpeResult keeps.
_RPE_ROTATION_FIELDS = ("rot_rmse_deg", "rot_mean_deg", "rot_median_deg", "rot_max_deg")


def _statistics(metric: evo_metrics.PE, unit_suffix: str, prefix: str = "") -> dict[str, float]:
    """evo's rmse/mean/median/max/min/std of a processed metric as result fields, e.g. ``rmse_m``."""
    stats = metric.get_all_statistics()
    return {
        f"{prefix}{name}{unit_suffix}": float(stats[name]) for name in ("rmse", "mean", "median", "max", "min", "std")
    }
