"""Reading the text tables of datasets (TUM lists, EuRoC CSVs, KITTI poses) with line numbers in errors.

Every reader goes through these helpers so that a malformed file always produces a ``DatasetError`` naming
``file:line`` and what was expected, never a numpy traceback.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from slamkit.errors import DatasetError

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass(frozen=True)
class TextRow:
    """One data line of a table: its 1-based line number in the file and its fields (stripped strings)."""

    line: int
    fields: list[str]


def require_dir(path: Path, what: str) -> Path:
    """Return ``path`` if it is a folder, else raise DatasetError saying which folder (``what``) is missing."""
    if not path.is_dir():
        raise DatasetError(f"{what}: folder {path} does not exist")
    return path


def require_file(path: Path, what: str) -> Path:
    """Return ``path`` if it is a file, else raise DatasetError saying which file (``what``) is missing."""
    if not path.is_file():
        raise DatasetError(f"{what}: file {path} does not exist")
    return path


def read_lines(path: Path, what: str = "table") -> list[str]:
    """All lines of the UTF-8 text file ``path`` (Windows line ends tolerated); DatasetError naming ``what``
    when the file is missing or unreadable."""
    require_file(path, what)
    try:
        return path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: cannot read {what} as UTF-8 text ({exc})") from exc


def split_rows(lines: Sequence[str], sep: str | None = None, comment: str = "#") -> list[TextRow]:
    """The data lines of ``lines`` split into fields; blank lines and lines starting with ``comment`` skipped.

    sep: None splits on any whitespace (TUM, KITTI); "," splits CSV fields (EuRoC).
    """
    rows: list[TextRow] = []
    for number, raw in enumerate(lines, start=1):
        line = raw.strip()
        if not line or line.startswith(comment):
            continue
        fields = [f.strip() for f in line.split(sep)] if sep is not None else line.split()
        rows.append(TextRow(number, fields))
    return rows


def read_rows(path: Path, sep: str | None = None, comment: str = "#", what: str = "table") -> list[TextRow]:
    """Split the data lines of a text table (see ``split_rows``)."""
    return split_rows(read_lines(path, what), sep, comment)


def row_lines(rows: Sequence[TextRow]) -> I64:
    """(N,) the 1-based file line of each row."""
    return np.array([r.line for r in rows], dtype=np.int64)


def _column_error(path: Path, row: TextRow, expected: str, what: str) -> DatasetError:
    shown = " ".join(row.fields)
    if len(shown) > 80:
        shown = shown[:77] + "..."
    return DatasetError(f"{path}:{row.line}: expected {expected} ({what}), got {len(row.fields)}: '{shown}'")


def check_columns(path: Path, rows: Sequence[TextRow], n_cols: int, what: str, at_least: bool = False) -> None:
    """Raise DatasetError naming the first line whose column count is not ``n_cols`` (or < it)."""
    for row in rows:
        n = len(row.fields)
        if n < n_cols or (not at_least and n != n_cols):
            expected = f"{'at least ' if at_least else ''}{n_cols} columns"
            raise _column_error(path, row, expected, what)


def parse_float(path: Path, row: TextRow, col: int, what: str) -> float:
    """Field ``col`` of ``row`` as a finite float, or DatasetError naming file, line and column."""
    text = row.fields[col]
    try:
        value = float(text)
    except ValueError:
        raise DatasetError(f"{path}:{row.line}: column {col + 1} should be a number ({what}), got '{text}'") from None
    if not np.isfinite(value):
        raise DatasetError(f"{path}:{row.line}: column {col + 1} should be finite ({what}), got '{text}'")
    return value


def parse_int(path: Path, row: TextRow, col: int, what: str) -> int:
    """Field ``col`` of ``row`` as an integer (e.g. EuRoC nanosecond stamps), or DatasetError."""
    text = row.fields[col]
    try:
        return int(text)
    except ValueError:
        raise DatasetError(f"{path}:{row.line}: column {col + 1} should be an integer ({what}), got '{text}'") from None


@dataclass(frozen=True)
class NumericTable:
    """A numeric table read from ``path``: values (N, C) float64 and the 1-based file line of each row."""

    path: Path
    values: F64
    lines: I64

    def __len__(self) -> int:
        return int(self.values.shape[0])


def float_columns(path: Path, rows: Sequence[TextRow], cols: Sequence[int], what: str) -> F64:
    """(N, len(cols)) float64: fields ``cols`` of every row, each a finite number (else DatasetError)."""
    values = np.empty((len(rows), len(cols)), dtype=np.float64)
    for i, row in enumerate(rows):
        for j, c in enumerate(cols):
            values[i, j] = parse_float(path, row, c, what)
    return values


def ns_column(path: Path, rows: Sequence[TextRow], col: int, what: str) -> F64:
    """(N,) s: field ``col`` of every row as integer nanoseconds (EuRoC stamps), converted with ``ns_to_s``."""
    return ns_to_s(np.array([parse_int(path, r, col, what) for r in rows], dtype=np.int64))


def read_numeric_table(
    path: Path, n_cols: int, sep: str | None = None, what: str = "table", at_least: bool = False
) -> NumericTable:
    """Read a table of ``n_cols`` numeric columns (``at_least``: extra columns are ignored)."""
    rows = read_rows(path, sep=sep, what=what)
    check_columns(path, rows, n_cols, what, at_least=at_least)
    return NumericTable(path, float_columns(path, rows, range(n_cols), what), row_lines(rows))


def ns_to_s(ns: I64) -> F64:
    """Integer nanoseconds -> float64 seconds, splitting whole seconds off first (float(ns) alone rounds ns to
    ~256 ns before scaling; the result is then exact to float64's ~2e-7 s at 1.4e9 s)."""
    whole = ns // 1_000_000_000
    return whole.astype(np.float64) + (ns - whole * 1_000_000_000).astype(np.float64) * 1e-9


def check_increasing(path: Path, t_s: F64, lines: I64, strict: bool = True, what: str = "timestamps") -> None:
    """Raise DatasetError naming the first line whose time is not after (or, non-strict, before) the previous.

    t_s: (N,) s; lines: (N,) the file line of each time.
    """
    if t_s.shape[0] < 2:
        return
    step = np.diff(t_s)
    bad = np.flatnonzero(step <= 0 if strict else step < 0)
    if bad.size:
        i = int(bad[0]) + 1
        order = "strictly increasing" if strict else "non-decreasing"
        raise DatasetError(
            f"{path}:{int(lines[i])}: {what} must be {order}; {float(t_s[i])!r} follows {float(t_s[i - 1])!r} "
            f"on line {int(lines[i - 1])}"
        )


@dataclass(frozen=True)
class StampedFiles:
    """A list of timestamped files (TUM rgb.txt / depth.txt, EuRoC cam data.csv).

    t_s: (N,) s strictly increasing; files: N absolute paths; lines: (N,) file line of each entry
    (0 when the list came from a folder listing); list_path: the list file (or the folder listed).
    """

    list_path: Path
    t_s: F64
    files: list[Path]
    lines: I64

    def __len__(self) -> int:
        return len(self.files)

    def check_files_exist(self) -> None:
        """Raise DatasetError naming the list line of the first entry when none of the listed files exists (a
        wrong folder, or a download without its images). A file missing here and there is a damaged recording:
        the run skips those frames (``runner.bad_frames``) and reports them."""
        if not self.files or any(path.is_file() for path in self.files):
            return
        path, line = self.files[0], self.lines[0]
        where = f"{self.list_path}:{int(line)}" if line > 0 else str(self.list_path)
        raise DatasetError(f"{where}: image file {path} listed there does not exist (nor does any other listed)")


def read_stamped_files(path: Path, base: Path, sep: str | None, ns_stamps: bool, what: str) -> StampedFiles:
    """Read a ``timestamp filename`` list; filenames are relative to ``base``.

    ns_stamps: the first column is integer nanoseconds (EuRoC) rather than float seconds (TUM).
    """
    rows = read_rows(path, sep=sep, what=what)
    check_columns(path, rows, 2, what)
    if ns_stamps:
        t_s = ns_column(path, rows, 0, what + " time [ns]")
    else:
        t_s = float_columns(path, rows, [0], what + " time [s]")[:, 0]
    lines = row_lines(rows)
    check_increasing(path, t_s, lines, strict=True, what=what + " timestamps")
    return StampedFiles(path, t_s, [base / r.fields[1] for r in rows], lines)


IMAGE_SUFFIXES: tuple[str, ...] = (".png", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm", ".tif", ".tiff")


def list_images(folder: Path, suffixes: Sequence[str] = IMAGE_SUFFIXES, what: str = "images") -> list[Path]:
    """Image files of ``folder`` (by suffix, case-insensitive), sorted by name; DatasetError when none."""
    require_dir(folder, what)
    wanted = {s.lower() if s.startswith(".") else "." + s.lower() for s in suffixes}
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in wanted)
    if not files:
        raise DatasetError(f"{what}: folder {folder} holds no image files with suffix {sorted(wanted)}")
    return files


def times_from_names(files: Sequence[Path], scale: float, what: str) -> F64:
    """Timestamps (N,) s read from numeric file stems (``1305031102.175304.png``), times ``scale``.

    Raises DatasetError naming the first file whose stem is not a number, or when times do not increase.
    """
    t = np.empty(len(files), dtype=np.float64)
    for i, f in enumerate(files):
        try:
            if scale == 1e-9 and f.stem.isdigit():
                # Nanosecond stems (EuRoC) exceed float64's 16 digits: split off whole seconds first.
                t[i] = float(ns_to_s(np.array([int(f.stem)], dtype=np.int64))[0])
            else:
                t[i] = float(f.stem) * scale
        except ValueError:
            raise DatasetError(
                f"{f}: {what}: file name should be a number (a timestamp) to take the time from it"
            ) from None
    steps = np.diff(t)
    if steps.size and np.any(steps <= 0):
        i = int(np.flatnonzero(steps <= 0)[0]) + 1
        raise DatasetError(f"{files[i]}: {what}: time from the name does not follow {files[i - 1].name}")
    return t
