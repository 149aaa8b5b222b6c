"""Read and write camera trajectories in the TUM, KITTI and EuRoC ground-truth formats.

Every reader returns a :class:`slamkit.sensors.Trajectory` (``t_s`` (N,) s, ``T_w_c`` (N, 4, 4) float64, the
pose written in the file). Quaternions exist only here, at the file boundary:

- TUM: ``t x y z qx qy qz qw`` per line (s, m, Hamilton quaternion), whitespace separated, ``#`` comments.
  TUM RGB-D ground truth is T_w_c of the colour camera's optical frame.
- KITTI: 12 numbers per line, the row-major top 3x4 block of ``T_w_c`` (camera 0; world = frame 0); no
  timestamps in the file. They come from a KITTI ``times.txt`` (one number per line, one per pose) when
  given, else the line index (0, 1, 2, ...).
- EuRoC ground truth (``state_groundtruth_estimate0/data.csv``): comma separated, ``#`` header line,
  timestamp in integer nanoseconds, ``p_RS_R`` x y z in metres, ``q_RS`` w x y z, then optional columns
  (velocities, biases) that are ignored. The poses are of the body (IMU) frame: T_w_b.

Validation rules (one set for every caller, dataset readers and ``slamkit eval`` alike):

- Column counts, numbers and finiteness are checked per line; the file must hold at least one pose.
- Trajectory timestamps must be non-decreasing: real ground truth repeats a stamp now and then (TUM fr2_desk
  does once; evo accepts it) but never goes back. KITTI ``times.txt`` (frame times) must strictly increase.
- A quaternion is accepted when ``| |q| - 1 | <= QUAT_NORM_TOL`` (1e-2: files round quaternions to ~4
  decimals) and normalised; anything further from unit length (a zero quaternion, fields that are not a
  quaternion at all) is an error rather than silently normalised.
- A KITTI 3x3 block must be a rotation: ``max |R^T R - I| <= ROTATION_TOL`` (1e-3; files store ~7
  significant digits) and det R > 0. A KITTI file needs exactly one time per pose.

Malformed input raises :class:`slamkit.errors.DatasetError` naming the file, the line and what was expected;
a format name that does not exist raises :class:`slamkit.errors.ConfigError`.
"""

from __future__ import annotations

from decimal import Decimal
from pathlib import Path
from typing import Literal, get_args

import numpy as np
from scipy.spatial.transform import Rotation

from slamkit.errors import ConfigError, DatasetError
from slamkit.io.textfiles import (
    I64,
    TextRow,
    check_columns,
    check_increasing,
    float_columns,
    ns_column,
    read_lines,
    read_numeric_table,
    row_lines,
    split_rows,
)
from slamkit.sensors import F64, Trajectory

TrajectoryFormat = Literal["tum", "kitti", "euroc"]
FORMATS: tuple[str, ...] = get_args(TrajectoryFormat)

#: | |q| - 1 | above this means the line does not hold a rotation quaternion.
QUAT_NORM_TOL = 1e-2
#: max |R^T R - I| above this means a KITTI 3x3 block is not a rotation.
ROTATION_TOL = 1e-3

_TUM_COLS = 8
_KITTI_COLS = 12
_EUROC_MIN_COLS = 8
_TUM_WHAT = "TUM trajectory 'timestamp tx ty tz qx qy qz qw'"
_KITTI_WHAT = "KITTI pose: 12 numbers of a row-major 3x4 [R|t] of T_w_c"
_EUROC_WHAT = "EuRoC ground truth 't[ns], px, py, pz, qw, qx, qy, qz, ...'"
_TIMES_WHAT = "KITTI time [s]"
_NS_PER_S = Decimal(10**9)


# ---------------------------------------------------------------------------------------------- checks


def _require_poses(path: Path, rows: list[TextRow], what: str) -> None:
    if not rows:
        raise DatasetError(f"{path}: no poses in the file (empty or only comments); expected {what}")


def _poses_from_quat(path: Path, lines: I64, xyz: F64, q_xyzw: F64) -> F64:
    """(N, 4, 4) T from positions (N, 3) m and quaternions (N, 4) x y z w, checked near unit and normalised."""
    norms = np.linalg.norm(q_xyzw, axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > QUAT_NORM_TOL)
    if bad.size:
        i = int(bad[0])
        raise DatasetError(
            f"{path}:{int(lines[i])}: quaternion norm is {norms[i]:.4f}; expected a unit quaternion "
            f"(| |q| - 1 | <= {QUAT_NORM_TOL})"
        )
    T = np.tile(np.eye(4), (xyz.shape[0], 1, 1))
    T[:, :3, :3] = Rotation.from_quat(q_xyzw).as_matrix()  # scalar-last; normalises
    T[:, :3, 3] = xyz
    return T


def _check_rotations(path: Path, lines: I64, R: F64) -> None:
    """R: (N, 3, 3); DatasetError naming the first line whose block is not a proper rotation."""
    ortho_err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    bad = np.flatnonzero((ortho_err > ROTATION_TOL) | (det <= 0))
    if bad.size:
        i = int(bad[0])
        raise DatasetError(
            f"{path}:{int(lines[i])}: the 3x3 block is not a rotation (max |R^T R - I| = {ortho_err[i]:.3g}, "
            f"det = {det[i]:.6g}); expected an orthonormal rotation with det +1"
        )


# ---------------------------------------------------------------------------------------------- parsers


def _parse_tum(path: Path, rows: list[TextRow]) -> Trajectory:
    check_columns(path, rows, _TUM_COLS, _TUM_WHAT)
    _require_poses(path, rows, _TUM_WHAT)
    v = float_columns(path, rows, range(_TUM_COLS), _TUM_WHAT)
    lines = row_lines(rows)
    check_increasing(path, v[:, 0], lines, strict=False, what="trajectory timestamps")
    return Trajectory(v[:, 0].copy(), _poses_from_quat(path, lines, v[:, 1:4], v[:, 4:8]))


def _parse_kitti(path: Path, rows: list[TextRow], times_path: Path | None) -> Trajectory:
    check_columns(path, rows, _KITTI_COLS, _KITTI_WHAT)
    _require_poses(path, rows, _KITTI_WHAT)
    n = len(rows)
    lines = row_lines(rows)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :] = float_columns(path, rows, range(_KITTI_COLS), _KITTI_WHAT).reshape(n, 3, 4)
    _check_rotations(path, lines, T[:, :3, :3])
    if times_path is None:
        return Trajectory(np.arange(n, dtype=np.float64), T)
    t_s = read_times(times_path)
    if t_s.shape[0] != n:
        raise DatasetError(f"{times_path}: {t_s.shape[0]} timestamps but {path} has {n} poses; expected one per pose")
    return Trajectory(t_s, T)


def _parse_euroc(path: Path, rows: list[TextRow]) -> Trajectory:
    check_columns(path, rows, _EUROC_MIN_COLS, _EUROC_WHAT, at_least=True)
    _require_poses(path, rows, _EUROC_WHAT)
    # Extra columns are optional, but a line shorter than its neighbours is a truncated line.
    n_cols = len(rows[0].fields)
    for row in rows:
        if len(row.fields) != n_cols:
            raise DatasetError(
                f"{path}:{row.line}: expected {n_cols} columns like line {rows[0].line} ({_EUROC_WHAT}), "
                f"got {len(row.fields)}"
            )
    t_s = ns_column(path, rows, 0, _EUROC_WHAT)
    lines = row_lines(rows)
    check_increasing(path, t_s, lines, strict=False, what="ground-truth timestamps")
    v = float_columns(path, rows, range(1, _EUROC_MIN_COLS), _EUROC_WHAT)
    q_xyzw = v[:, [4, 5, 6, 3]]  # the file stores w x y z
    return Trajectory(t_s, _poses_from_quat(path, lines, v[:, 0:3], q_xyzw))


# ---------------------------------------------------------------------------------------------- per-format readers


def read_tum_trajectory(path: Path) -> Trajectory:
    """Read a TUM trajectory file (``timestamp tx ty tz qx qy qz qw`` per line); poses as written."""
    return _parse_tum(path, split_rows(read_lines(path, _TUM_WHAT)))


def read_euroc_groundtruth(path: Path) -> Trajectory:
    """Read EuRoC ``state_groundtruth_estimate0/data.csv``: T_w_b, the body (IMU) poses in the world.

    The EuRoC dataset reader turns them into camera poses (``transform_trajectory`` with T_b_c).
    """
    return _parse_euroc(path, split_rows(read_lines(path, _EUROC_WHAT), sep=","))


def read_kitti_poses(path: Path, times_path: Path | None = None) -> Trajectory:
    """Read KITTI ``poses/NN.txt``: T_w_c of camera 0 per line; times from ``times_path`` (one per pose),
    else the 0-based line index."""
    return _parse_kitti(path, split_rows(read_lines(path, _KITTI_WHAT)), times_path)


def read_times(path: str | Path) -> F64:
    """A KITTI ``times.txt``: one timestamp (s) per line, strictly increasing. Returns (N,) float64, N >= 1."""
    path = Path(path)
    table = read_numeric_table(path, 1, what=_TIMES_WHAT)
    if len(table) == 0:
        raise DatasetError(f"{path}: no timestamps in the file; expected one time in seconds per line")
    t_s = table.values[:, 0].copy()
    check_increasing(path, t_s, table.lines, strict=True, what="KITTI times")
    return t_s


# ---------------------------------------------------------------------------------------------- any format


def _detect(path: Path, lines: list[str]) -> TrajectoryFormat:
    for lineno, raw in enumerate(lines, start=1):
        text = raw.strip()
        if not text:
            continue
        if text.startswith("#"):
            # The EuRoC header ("#timestamp, p_RS_R_x [m], ...") is the only comma-separated comment we know.
            if "," in text and "timestamp" in text.lower():
                return "euroc"
            continue
        if "," in text:
            return "euroc"
        ncols = len(text.split())
        if ncols == _TUM_COLS:
            return "tum"
        if ncols == _KITTI_COLS:
            return "kitti"
        raise DatasetError(
            f"{path}:{lineno}: cannot tell the trajectory format from {ncols} columns; expected 8 (TUM "
            "'t x y z qx qy qz qw'), 12 (KITTI 3x4 pose) or a comma-separated EuRoC CSV"
        )
    raise DatasetError(
        f"{path}: no poses in the file (empty or only comments); expected a TUM, KITTI or EuRoC trajectory"
    )


def detect_format(path: str | Path) -> TrajectoryFormat:
    """The format of a trajectory file, from its first data line: commas (or an EuRoC ``#timestamp, ...``
    header) -> "euroc", 8 whitespace-separated columns -> "tum", 12 -> "kitti". DatasetError otherwise."""
    path = Path(path)
    return _detect(path, read_lines(path, "trajectory file"))


def _check_format(fmt: str, parameter: str, allow_auto: bool) -> None:
    valid = (*FORMATS, "auto") if allow_auto else FORMATS
    if fmt not in valid:
        raise ConfigError(f"{parameter}={fmt!r} is not a trajectory format; expected one of {list(valid)}")


def read_trajectory(path: str | Path, fmt: str = "auto", times_path: str | Path | None = None) -> Trajectory:
    """Read a trajectory file into a Trajectory (t_s (N,) s, T_w_c (N, 4, 4)).

    fmt: "auto" (detect from the content), "tum", "kitti" or "euroc".
    times_path: KITTI only, a times.txt with one timestamp (s) per pose; without it KITTI poses get their
    0-based line index as timestamp.
    """
    _check_format(fmt, "fmt", allow_auto=True)
    path = Path(path)
    lines = read_lines(path, "trajectory file")
    resolved = _detect(path, lines) if fmt == "auto" else fmt
    if times_path is not None and resolved != "kitti":
        raise ConfigError(f"times_path is only for KITTI trajectories, but {path} is read as {resolved!r}")
    if resolved == "tum":
        return _parse_tum(path, split_rows(lines))
    if resolved == "kitti":
        return _parse_kitti(path, split_rows(lines), None if times_path is None else Path(times_path))
    return _parse_euroc(path, split_rows(lines, sep=","))


# ---------------------------------------------------------------------------------------------- writer


def _num(v: float) -> str:
    # repr is the shortest text that reads back to the same float64: the round trip is exact.
    return repr(float(v))


def write_trajectory(path: str | Path, traj: Trajectory, fmt: str, times_path: str | Path | None = None) -> None:
    """Write a Trajectory as "tum", "kitti" or "euroc" (8 columns: no velocities or biases).

    Numbers are written with full float64 precision (TUM/KITTI read back bit for bit; EuRoC timestamps are
    rounded to integer nanoseconds). times_path: KITTI only, also write the timestamps there (times.txt).
    Raises DatasetError (nothing written) when a timestamp or pose is not finite.
    """
    _check_format(fmt, "fmt", allow_auto=False)
    path = Path(path)
    if times_path is not None and fmt != "kitti":
        raise ConfigError(f"times_path is only for KITTI trajectories, not fmt={fmt!r}")
    bad = np.flatnonzero(~np.isfinite(traj.T_w_c).all(axis=(1, 2)) | ~np.isfinite(traj.t_s))
    if bad.size:
        raise DatasetError(f"{path}: pose {int(bad[0])} has a non-finite timestamp or pose; not written")
    out: list[str] = []
    if fmt == "kitti":
        out.extend(" ".join(_num(v) for v in T[:3, :4].ravel()) for T in traj.T_w_c)
    else:
        quats = Rotation.from_matrix(traj.T_w_c[:, :3, :3]).as_quat() if len(traj) else np.zeros((0, 4))
        if fmt == "tum":
            out.append("# timestamp tx ty tz qx qy qz qw")
            for t, T, q in zip(traj.t_s, traj.T_w_c, quats, strict=True):
                out.append(" ".join(_num(v) for v in (t, *T[:3, 3], *q)))
        else:
            out.append(
                "#timestamp [ns], p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []"
            )
            for t, T, q in zip(traj.t_s, traj.T_w_c, quats, strict=True):
                ns = int((Decimal(float(t)) * _NS_PER_S).to_integral_value())
                out.append(",".join([str(ns), *(_num(v) for v in (*T[:3, 3], q[3], q[0], q[1], q[2]))]))
    try:
        path.write_text("\n".join(out) + "\n", encoding="utf-8")
        if times_path is not None:
            Path(times_path).write_text("".join(_num(t) + "\n" for t in traj.t_s), encoding="utf-8")
    except OSError as exc:
        raise DatasetError(f"{path}: cannot write trajectory ({exc})") from exc
