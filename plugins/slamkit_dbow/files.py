"""Loading and saving a vocabulary in either format, chosen by the file name: ``*.txt`` / ``*.txt.gz`` is
DBoW2's text format (ORBvoc.txt), ``*.skvoc`` slamkit's binary form."""

from __future__ import annotations

from pathlib import Path

from slamkit.errors import DatasetError
from slamkit_dbow.binformat import BINARY_SUFFIX, MAGIC, read_binary_vocabulary, write_binary_vocabulary
from slamkit_dbow.textformat import read_text_vocabulary, write_text_vocabulary
from slamkit_dbow.vocabulary import Vocabulary


def is_text_path(path: str | Path) -> bool:
    """True for DBoW2 text files: names ending in .txt or .txt.gz."""
    name = Path(path).name.lower()
    return name.endswith(".txt") or name.endswith(".txt.gz")


def load_vocabulary(path: str | Path) -> Vocabulary:
    """Read a vocabulary file: DBoW2 text (.txt, .txt.gz) or slamkit binary (.skvoc, or any file that starts
    with the binary magic)."""
    p = Path(path)
    if not p.is_file():
        raise DatasetError(f"{p}: vocabulary file not found")
    if is_text_path(p):
        return read_text_vocabulary(p)
    with open(p, "rb") as f:
        head = f.read(len(MAGIC) - 1)
    if head == MAGIC[:-1]:
        return read_binary_vocabulary(p)
    raise DatasetError(
        f"{p}: unknown vocabulary format: expected a DBoW2 text file named *.txt / *.txt.gz or a slamkit "
        f"binary vocabulary (*{BINARY_SUFFIX})"
    )


def save_vocabulary(vocab: Vocabulary, path: str | Path, text_precision: int | None = None) -> None:
    """Write a vocabulary: DBoW2 text for *.txt / *.txt.gz (weights with ``text_precision`` significant
    digits, None = exact), slamkit binary otherwise. The parent folder is created if needed."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    if is_text_path(p):
        write_text_vocabulary(vocab, p, text_precision)
    else:
        write_binary_vocabulary(vocab, p)
