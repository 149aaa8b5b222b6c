"""DBoW2's text vocabulary format, the one of ORB-SLAM's ORBvoc.txt (TemplatedVocabulary::saveToTextFile /
loadFromTextFile, as modified by ORB-SLAM)::

    10 6  0 0
    0 0 252 188 188 242 ... 112 134 34  0
    ...

Line 1: ``k L scoring weighting`` (ORB-SLAM writes two spaces before the scoring code). Then one line per
node, node 1 first (the root, node 0, is implicit): ``parent_id is_leaf`` then the node's descriptor as
D decimal byte values (D = 32 for ORB) each followed by a space, then a space and the weight. Word ids are
given to the leaves in line order. DBoW2's reader accepts any whitespace between tokens; so does ours.
A ``.gz`` file is read and written gzip-compressed.
"""

from __future__ import annotations

import gzip
import warnings
from pathlib import Path
from typing import IO, cast

import numpy as np

from slamkit.errors import DatasetError
from slamkit_dbow.kernels import tokens_per_line
from slamkit_dbow.vocabulary import Scoring, Vocabulary, VocabularyError, Weighting

#: Bytes of an ORB descriptor (DBoW2's FORB::L), the width of every node in the text format.
ORB_DESCRIPTOR_BYTES = 32
_BYTE_TEXT = [str(i) for i in range(256)]


def _open_text(path: Path, mode: str) -> IO[str]:
    if path.suffix == ".gz":
        return cast(IO[str], gzip.open(path, mode + "t", encoding="ascii", newline="\n"))
    return open(path, mode, encoding="ascii", newline="\n")


def _format_weight(w: float, precision: int | None) -> str:
    if w == 0.0:
        return "0"
    if precision is not None:
        return f"{w:.{precision}g}"  # C++ ostream default formatting with that precision
    text = repr(float(w))  # shortest text that reads back to the same double
    return text[:-2] if text.endswith(".0") else text


def write_text_vocabulary(vocab: Vocabulary, path: str | Path, precision: int | None = None) -> None:
    """Write ``vocab`` in DBoW2's text format (readable by ORB-SLAM's ``loadFromTextFile``).

    precision: significant digits of the weights; None (default) writes the shortest text that reads back
    to the same double, so reading the file gives identical BoW vectors. ORB-SLAM's own writer uses the
    C++ default, 6 (pass precision=6 to mimic it byte for byte).
    """
    if vocab.descriptor_bytes != ORB_DESCRIPTOR_BYTES:
        raise VocabularyError(
            f"DBoW2's text format holds {ORB_DESCRIPTOR_BYTES}-byte ORB descriptors; this vocabulary has "
            f"{vocab.descriptor_bytes}-byte ones"
        )
    path = Path(path)
    with _open_text(path, "w") as f:
        f.write(f"{vocab.k} {vocab.L}  {int(vocab.scoring)} {int(vocab.weighting)}\n")
        desc = vocab.descriptors
        for i in range(1, vocab.n_nodes):
            row = " ".join([_BYTE_TEXT[b] for b in desc[i].tolist()])
            leaf = 1 if vocab.is_leaf[i] else 0
            f.write(f"{vocab.parent[i]} {leaf} {row}  {_format_weight(float(vocab.weights[i]), precision)}\n")


def _parse_header(line: str, where: str) -> tuple[int, int, int, int]:
    parts = line.split()
    try:
        if len(parts) != 4:
            raise ValueError
        k, L, scoring, weighting = (int(p) for p in parts)
    except ValueError:
        raise DatasetError(
            f"{where}:1: expected the header 'k L scoring weighting' (4 integers), got {line!r}"
        ) from None
    # DBoW2's own sanity limits (loadFromTextFile)
    if not (0 <= k <= 20 and 1 <= L <= 10 and 0 <= scoring <= 5 and 0 <= weighting <= 3):
        raise DatasetError(
            f"{where}:1: header {line.strip()!r} out of range: expected 0 <= k <= 20, 1 <= L <= 10, "
            "0 <= scoring <= 5, 0 <= weighting <= 3"
        )
    return k, L, scoring, weighting


def _row_errors(rows: np.ndarray) -> str | None:
    """First problem of parsed node rows (n, 35): None when every row is a valid node line."""
    ids = np.arange(1, rows.shape[0] + 1)
    checks = (
        (np.any(rows[:, :-1] != np.round(rows[:, :-1]), axis=1), "parent, is_leaf and the bytes must be integers"),
        ((rows[:, 0] < 0) | (rows[:, 0] >= ids), "parent id must be smaller than the node's own id (its line - 1)"),
        ((rows[:, 1] != 0) & (rows[:, 1] != 1), "is_leaf must be 0 or 1"),
        (np.any((rows[:, 2:-1] < 0) | (rows[:, 2:-1] > 255), axis=1), "descriptor bytes must be in [0, 255]"),
        (~np.isfinite(rows[:, -1]) | (rows[:, -1] < 0), "weight must be a finite number >= 0"),
    )
    for bad, what in checks:
        if np.any(bad):
            return f"{int(np.flatnonzero(bad)[0])}:{what}"
    return None


def read_text_vocabulary(path: str | Path) -> Vocabulary:
    """Read a vocabulary in DBoW2's text format (ORBvoc.txt, or ORBvoc.txt.gz).

    Parsing is vectorised (ORBvoc.txt, 1.08 M nodes, 145 MB, loads in seconds); convert it once to the
    binary form for fast loads. Raises DatasetError naming the file and line for a malformed file.
    """
    path = Path(path)
    where = str(path)
    if not path.is_file():
        raise DatasetError(f"{where}: vocabulary file not found")
    try:
        with _open_text(path, "r") as f:
            header = f.readline()
            body = f.read()
    except (OSError, UnicodeDecodeError, EOFError, gzip.BadGzipFile) as exc:
        raise DatasetError(f"{where}: cannot read the vocabulary text file: {exc}") from None
    k, L, scoring, weighting = _parse_header(header, where)
    n_tok = 2 + ORB_DESCRIPTOR_BYTES + 1
    per_line = tokens_per_line(np.frombuffer(body.encode("ascii"), np.uint8))
    node_lines = np.flatnonzero(per_line > 0)  # 0-based line index in the body; file line = index + 2
    wrong = node_lines[per_line[node_lines] != n_tok]
    if wrong.size:
        line = int(wrong[0])
        raise DatasetError(
            f"{where}:{line + 2}: expected {n_tok} values 'parent is_leaf <{ORB_DESCRIPTOR_BYTES} bytes> weight', "
            f"got {int(per_line[line])}"
        )
    if node_lines.size == 0:
        raise DatasetError(f"{where}: the vocabulary has no node after its header")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            flat = np.fromstring(body, dtype=np.float64, sep=" ")
    except (ValueError, DeprecationWarning):
        flat = np.zeros(0)
    if flat.size != node_lines.size * n_tok:  # a token that is not a number: find its line
        lines = body.split("\n")
        for line in node_lines.tolist():
            for tok in lines[line].split():
                try:
                    float(tok)
                except ValueError:
                    raise DatasetError(f"{where}:{int(line) + 2}: {tok!r} is not a number") from None
        raise DatasetError(f"{where}: cannot parse the node lines as numbers")
    rows = flat.reshape(-1, n_tok)
    err = _row_errors(rows)
    if err is not None:
        row, what = err.split(":", 1)
        raise DatasetError(f"{where}:{int(node_lines[int(row)]) + 2}: {what}")
    n = rows.shape[0] + 1
    parent = np.concatenate(([-1], rows[:, 0].astype(np.int32)))
    is_leaf = np.concatenate(([False], rows[:, 1] > 0))
    desc = np.zeros((n, ORB_DESCRIPTOR_BYTES), np.uint8)
    desc[1:] = rows[:, 2:-1].astype(np.uint8)
    weights = np.concatenate(([0.0], rows[:, -1]))
    try:
        return Vocabulary(k, L, parent, desc, weights, is_leaf, Scoring(scoring), Weighting(weighting))
    except VocabularyError as exc:
        raise DatasetError(f"{where}: {exc} (node i is on line i + 1 of the file)") from None
