"""Read and write camera trajectories in the TUM, KITTI and EuRoC ground-truth formats.

Every reader returns a :class:`slamkit.sensors.Trajectory` (``t_s`` (N,) s, ``T_w_c`` (N, 4, 4) float64,
pose of the camera in the world). Quaternions exist only here, at the file boundary:

- TUM: ``t x y z qx qy qz qw`` per line, whitespace separated, ``#`` comment lines.
- KITTI: 12 numbers per line, the row-major top 3x4 block of ``T_w_c``; no timestamps in the file. They come
  from a KITTI ``times.txt`` (one number per line) when given, else the line index (0, 1, 2, ...).
- EuRoC ground truth (``state_groundtruth_estimate0/data.csv``): comma separated, ``#`` header line,
  timestamp in integer nanoseconds, ``p_RS_R`` x y z in metres, ``q_RS`` w x y z, then optional columns
  (velocities, biases) that are ignored.

Malformed input raises :class:`slamkit.errors.DatasetError` naming the file, the line and what was expected.
"""

from __future__ import annotations

from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import Literal, get_args

import numpy as np
from scipy.spatial.transform import Rotation

from slamkit.errors import ConfigError, DatasetError
from slamkit.sensors import F64, Trajectory

TrajectoryFormat = Literal["tum", "kitti", "euroc"]
FORMATS: tuple[str, ...] = get_args(TrajectoryFormat)

_TUM_COLS = 8
_KITTI_COLS = 12
_EUROC_MIN_COLS = 8
# A KITTI rotation block this far from orthonormal is not a pose (files store ~7 significant digits).
_ROTATION_TOL = 1e-3
_NS_PER_S = Decimal(10**9)


def _read_lines(path: Path) -> list[str]:
    try:
        return path.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise DatasetError(f"{path}: trajectory file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: cannot read trajectory file ({exc})") from exc


def _data_lines(lines: list[str]) -> list[tuple[int, str]]:
    """(1-based line number, stripped text) of every line that is neither blank nor a '#' comment."""
    out: list[tuple[int, str]] = []
    for lineno, raw in enumerate(lines, start=1):
        text = raw.strip()
        if text and not text.startswith("#"):
            out.append((lineno, text))
    return out


def _split(path: Path, lineno: int, text: str, sep: str | None, expected: str) -> list[str]:
    fields = [f.strip() for f in text.split(sep)] if sep else text.split()
    if any(f == "" for f in fields):
        raise DatasetError(f"{path}:{lineno}: empty field in {text!r}; expected {expected}")
    return fields


def _floats(path: Path, lineno: int, fields: list[str], expected: str) -> list[float]:
    try:
        values = [float(f) for f in fields]
    except ValueError:
        raise DatasetError(f"{path}:{lineno}: non-numeric value in {' '.join(fields)!r}; expected {expected}") from None
    if not all(np.isfinite(values)):
        raise DatasetError(f"{path}:{lineno}: non-finite value (nan/inf); expected {expected}")
    return values


def _check_times(path: Path, linenos: list[int], t_s: F64) -> None:
    """Timestamps must be non-decreasing (real ground truth repeats a stamp now and then, never goes back)."""
    back = np.flatnonzero(np.diff(t_s) < 0)
    if back.size:
        i = int(back[0]) + 1
        raise DatasetError(
            f"{path}:{linenos[i]}: timestamp {float(t_s[i])!r} is before the previous one {float(t_s[i - 1])!r} "
            f"(line {linenos[i - 1]}); expected non-decreasing timestamps"
        )


def _poses_from_quat(path: Path, linenos: list[int], xyz: F64, quat_xyzw: F64) -> F64:
    """(N, 4, 4) T_w_c from positions (N, 3) m and quaternions (N, 4) x y z w, normalised here."""
    norms = np.linalg.norm(quat_xyzw, axis=1)
    bad = np.flatnonzero(norms < 1e-12)
    if bad.size:
        raise DatasetError(f"{path}:{linenos[int(bad[0])]}: zero quaternion; expected a unit quaternion")
    T = np.tile(np.eye(4), (xyz.shape[0], 1, 1))
    T[:, :3, :3] = Rotation.from_quat(quat_xyzw / norms[:, None]).as_matrix()
    T[:, :3, 3] = xyz
    return T


def _empty(path: Path, what: str) -> DatasetError:
    return DatasetError(f"{path}: no poses in the file (empty or only comments); expected {what}")


def _read_tum(path: Path, lines: list[str]) -> Trajectory:
    expected = "8 numbers 't x y z qx qy qz qw' (TUM)"
    rows: list[list[float]] = []
    linenos: list[int] = []
    for lineno, text in _data_lines(lines):
        fields = _split(path, lineno, text, None, expected)
        if len(fields) != _TUM_COLS:
            raise DatasetError(f"{path}:{lineno}: {len(fields)} columns; expected {expected}")
        rows.append(_floats(path, lineno, fields, expected))
        linenos.append(lineno)
    if not rows:
        raise _empty(path, expected)
    mat = np.asarray(rows, dtype=np.float64)
    _check_times(path, linenos, mat[:, 0])
    return Trajectory(mat[:, 0].copy(), _poses_from_quat(path, linenos, mat[:, 1:4], mat[:, 4:8]))


def read_times(path: str | Path) -> F64:
    """A KITTI ``times.txt``: one timestamp (s) per line, non-decreasing. Returns (N,) float64."""
    path = Path(path)
    expected = "one timestamp in seconds per line (KITTI times.txt)"
    values: list[float] = []
    linenos: list[int] = []
    for lineno, text in _data_lines(_read_lines(path)):
        fields = _split(path, lineno, text, None, expected)
        if len(fields) != 1:
            raise DatasetError(f"{path}:{lineno}: {len(fields)} columns; expected {expected}")
        values.extend(_floats(path, lineno, fields, expected))
        linenos.append(lineno)
    if not values:
        raise DatasetError(f"{path}: no timestamps in the file; expected {expected}")
    t_s = np.asarray(values, dtype=np.float64)
    _check_times(path, linenos, t_s)
    return t_s


def _read_kitti(path: Path, lines: list[str], times_path: Path | None) -> Trajectory:
    expected = "12 numbers per line, the row-major 3x4 [R|t] of T_w_c (KITTI)"
    rows: list[list[float]] = []
    linenos: list[int] = []
    for lineno, text in _data_lines(lines):
        fields = _split(path, lineno, text, None, expected)
        if len(fields) != _KITTI_COLS:
            raise DatasetError(f"{path}:{lineno}: {len(fields)} columns; expected {expected}")
        rows.append(_floats(path, lineno, fields, expected))
        linenos.append(lineno)
    if not rows:
        raise _empty(path, expected)
    n = len(rows)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :4] = np.asarray(rows, dtype=np.float64).reshape(n, 3, 4)
    R = T[:, :3, :3]
    ortho_err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((ortho_err > _ROTATION_TOL) | (np.linalg.det(R) <= 0))
    if bad.size:
        i = int(bad[0])
        raise DatasetError(
            f"{path}:{linenos[i]}: the 3x3 block is not a rotation (max |R^T R - I| = {ortho_err[i]:.3g}, "
            f"det = {np.linalg.det(R[i]):.6g}); expected an orthonormal rotation with det +1"
        )
    if times_path is None:
        t_s = np.arange(n, dtype=np.float64)
    else:
        t_s = read_times(times_path)
        if t_s.shape[0] != n:
            raise DatasetError(
                f"{times_path}: {t_s.shape[0]} timestamps but {path} has {n} poses; expected one per pose"
            )
    return Trajectory(t_s, T)


def _euroc_seconds(path: Path, lineno: int, field: str, expected: str) -> float:
    # Nanosecond stamps (~1.4e18) do not fit float64 exactly: parse exactly, then round once to seconds.
    try:
        ns = Decimal(field)
    except InvalidOperation:
        raise DatasetError(f"{path}:{lineno}: non-numeric timestamp {field!r}; expected {expected}") from None
    if not ns.is_finite():
        raise DatasetError(f"{path}:{lineno}: non-finite timestamp {field!r}; expected {expected}")
    return float(ns / _NS_PER_S)


def _read_euroc(path: Path, lines: list[str]) -> Trajectory:
    expected = "comma-separated 'timestamp[ns], px, py, pz, qw, qx, qy, qz[, ...]' (EuRoC ground truth)"
    t: list[float] = []
    rows: list[list[float]] = []
    linenos: list[int] = []
    ncols: int | None = None
    for lineno, text in _data_lines(lines):
        fields = _split(path, lineno, text, ",", expected)
        if ncols is None:
            if len(fields) < _EUROC_MIN_COLS:
                raise DatasetError(f"{path}:{lineno}: {len(fields)} columns; expected {expected}")
            ncols = len(fields)
        elif len(fields) != ncols:
            raise DatasetError(
                f"{path}:{lineno}: {len(fields)} columns; expected {ncols} like line {linenos[0]} ({expected})"
            )
        t.append(_euroc_seconds(path, lineno, fields[0], expected))
        rows.append(_floats(path, lineno, fields[1:_EUROC_MIN_COLS], expected))
        linenos.append(lineno)
    if not rows:
        raise _empty(path, expected)
    t_s = np.asarray(t, dtype=np.float64)
    _check_times(path, linenos, t_s)
    mat = np.asarray(rows, dtype=np.float64)
    quat_xyzw = mat[:, [4, 5, 6, 3]]  # the file stores w x y z
    return Trajectory(t_s, _poses_from_quat(path, linenos, mat[:, 0:3], quat_xyzw))


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
    raise _empty(path, "a TUM, KITTI or EuRoC trajectory")


def detect_format(path: str | Path) -> TrajectoryFormat:
    """The format of a trajectory file, from its content: a comma-separated line or EuRoC header -> "euroc",
    else 8 whitespace-separated columns -> "tum", 12 -> "kitti". Raises DatasetError otherwise."""
    path = Path(path)
    return _detect(path, _read_lines(path))


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
    lines = _read_lines(path)
    resolved = _detect(path, lines) if fmt == "auto" else fmt
    if times_path is not None and resolved != "kitti":
        raise ConfigError(f"times_path is only for KITTI trajectories, but {path} is read as {resolved!r}")
    if resolved == "tum":
        return _read_tum(path, lines)
    if resolved == "kitti":
        return _read_kitti(path, lines, None if times_path is None else Path(times_path))
    return _read_euroc(path, lines)


def _num(v: float) -> str:
    # repr is the shortest text that reads back to the same float64: the round trip is exact.
    return repr(float(v))


def write_trajectory(path: str | Path, traj: Trajectory, fmt: str, times_path: str | Path | None = None) -> None:
    """Write a Trajectory as "tum", "kitti" or "euroc" (8 columns: no velocities or biases).

    Numbers are written with full float64 precision (TUM/KITTI read back bit for bit; EuRoC timestamps are
    rounded to integer nanoseconds). times_path: KITTI only, also write the timestamps there (times.txt).
    """
    _check_format(fmt, "fmt", allow_auto=False)
    path = Path(path)
    if times_path is not None and fmt != "kitti":
        raise ConfigError(f"times_path is only for KITTI trajectories, not fmt={fmt!r}")
    bad = np.flatnonzero(~np.isfinite(traj.T_w_c).all(axis=(1, 2)) | ~np.isfinite(traj.t_s))
    if bad.size:
        raise DatasetError(f"{path}: pose {int(bad[0])} has a non-finite timestamp or pose; not written")
    out: list[str] = []
    if fmt == "tum":
        out.append("# timestamp tx ty tz qx qy qz qw")
        quats = Rotation.from_matrix(traj.T_w_c[:, :3, :3]).as_quat() if len(traj) else np.zeros((0, 4))
        for t, T, q in zip(traj.t_s, traj.T_w_c, quats, strict=True):
            out.append(" ".join(_num(v) for v in (t, *T[:3, 3], *q)))
    elif fmt == "kitti":
        out.extend(" ".join(_num(v) for v in T[:3, :4].ravel()) for T in traj.T_w_c)
    else:
        out.append(
            "#timestamp [ns], p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []"
        )
        quats = Rotation.from_matrix(traj.T_w_c[:, :3, :3]).as_quat() if len(traj) else np.zeros((0, 4))
        for t, T, q in zip(traj.t_s, traj.T_w_c, quats, strict=True):
            ns = int((Decimal(float(t)) * _NS_PER_S).to_integral_value())
            out.append(",".join([str(ns), *(_num(v) for v in (*T[:3, 3], q[3], q[0], q[1], q[2]))]))
    try:
        path.write_text("\n".join(out) + "\n", encoding="utf-8")
        if times_path is not None:
            Path(times_path).write_text("".join(_num(t) + "\n" for t in traj.t_s), encoding="utf-8")
    except OSError as exc:
        raise DatasetError(f"{path}: cannot write trajectory ({exc})") from exc
