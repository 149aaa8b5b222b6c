"""DBoW2 text format (ORBvoc.txt's layout) and slamkit's binary form: exact layout, round trips, errors."""

from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray
from slamkit_dbow.binformat import read_binary_vocabulary, vocabulary_to_bytes, write_binary_vocabulary
from slamkit_dbow.files import load_vocabulary, save_vocabulary
from slamkit_dbow.textformat import read_text_vocabulary, write_text_vocabulary
from slamkit_dbow.vocabulary import Scoring, Vocabulary, Weighting

from slamkit.errors import DatasetError


def _row(value: int) -> str:
    return " ".join(str(value) for _ in range(32))


#: A hand-made vocabulary in exactly ORBvoc.txt's layout: header "k L  scoring weighting" (two spaces),
#: then "parent is_leaf <32 bytes> " + " " + weight (the descriptor is followed by a space, then " w").
#: k=2, L=2: root -> nodes 1 (bytes 0) and 2 (bytes 255); node 1 -> words 3, 4; node 2 -> words 5, 6.
HAND_MADE = (
    "2 2  0 0\n"
    f"0 0 {_row(0)}  0\n"
    f"0 0 {_row(255)}  0\n"
    f"1 1 {_row(0)}  1.5\n"
    f"1 1 {_row(15)}  0.25\n"
    f"2 1 {_row(255)}  2\n"
    f"2 1 {_row(240)}  0\n"
)


def test_reads_a_hand_made_file_in_orbvoc_layout(tmp_path: Path) -> None:
    path = tmp_path / "ORBvoc.txt"
    path.write_text(HAND_MADE)
    v = read_text_vocabulary(path)
    assert (v.k, v.L, v.scoring, v.weighting) == (2, 2, Scoring.L1_NORM, Weighting.TF_IDF)
    assert v.n_nodes == 7 and v.n_words == 4
    assert v.parent.tolist() == [-1, 0, 0, 1, 1, 2, 2]
    assert v.is_leaf.tolist() == [False, False, False, True, True, True, True]
    assert v.word_nodes.tolist() == [3, 4, 5, 6]  # word ids in line order
    assert v.word_weights.tolist() == [1.5, 0.25, 2.0, 0.0]
    assert v.descriptors[4].tolist() == [15] * 32 and v.descriptors[6].tolist() == [240] * 32
    # transform: all-zero bytes -> node 1 -> word 0 (node 3); 0x0F bytes -> word 1; 0xFF -> word 2;
    # 0xF8 bytes (closer to 0xFF than to 0x00, then to 0xF0) reach word 3, whose weight 0 stops it
    # (DBoW2 drops such features from the vector and the direct index)
    desc = np.array([[0] * 32, [15] * 32, [15] * 32, [255] * 32, [248] * 32], np.uint8)
    bow = v.transform(desc, 1)
    total = 1.5 + 2 * 0.25 + 2.0
    assert bow.words == pytest.approx({0: 1.5 / total, 1: 0.5 / total, 2: 2.0 / total})
    assert {k: d.tolist() for k, d in bow.direct_index.items()} == {1: [0, 1, 2], 2: [3]}


def test_writer_reproduces_the_orbvoc_layout_byte_for_byte(tmp_path: Path) -> None:
    src = tmp_path / "in.txt"
    src.write_text(HAND_MADE)
    out = tmp_path / "out.txt"
    write_text_vocabulary(read_text_vocabulary(src), out)
    assert out.read_text() == HAND_MADE
    write_text_vocabulary(read_text_vocabulary(src), out, precision=6)  # ORB-SLAM's own writer: 6 digits
    assert out.read_text() == HAND_MADE


def _bows_equal(a: Vocabulary, b: Vocabulary, images: list[NDArray[np.uint8]]) -> None:
    for d in images:
        ba, bb = a.transform(d, 2), b.transform(d, 2)
        assert ba.words == bb.words  # identical floats, not approximately
        assert ba.direct_index.keys() == bb.direct_index.keys()
        assert all(np.array_equal(ba.direct_index[n], bb.direct_index[n]) for n in ba.direct_index)


@pytest.mark.parametrize("name", ["voc.txt", "voc.txt.gz", "voc.skvoc"])
def test_round_trip_gives_identical_bow_vectors(
    tmp_path: Path, name: str, small_vocab: Vocabulary, room_descriptors: list[NDArray[np.uint8]]
) -> None:
    path = tmp_path / name
    save_vocabulary(small_vocab, path)
    back = load_vocabulary(path)
    assert back.same_as(small_vocab)
    _bows_equal(small_vocab, back, room_descriptors)
    if name.endswith(".gz"):
        assert gzip.decompress(path.read_bytes()).startswith(b"6 3  0 0\n")


def test_text_with_six_digits_is_close_but_rounded(tmp_path: Path, small_vocab: Vocabulary) -> None:
    path = tmp_path / "voc6.txt"
    write_text_vocabulary(small_vocab, path, precision=6)
    back = read_text_vocabulary(path)
    assert np.allclose(back.weights, small_vocab.weights, rtol=1e-5) and np.array_equal(back.parent, small_vocab.parent)
    lines = path.read_text().splitlines()
    assert lines[0] == "6 3  0 0" and len(lines) == small_vocab.n_nodes
    assert "  " in lines[1] and len(lines[1].split()) == 35


def test_binary_is_deterministic_and_keeps_metadata(tmp_path: Path, small_vocab: Vocabulary) -> None:
    assert vocabulary_to_bytes(small_vocab) == vocabulary_to_bytes(small_vocab)
    small_vocab.metadata["note"] = "x"
    try:
        write_binary_vocabulary(small_vocab, tmp_path / "v.skvoc")
        assert read_binary_vocabulary(tmp_path / "v.skvoc").metadata["note"] == "x"
    finally:
        del small_vocab.metadata["note"]


def test_binary_corruption_is_reported(tmp_path: Path, small_vocab: Vocabulary) -> None:
    data = bytearray(vocabulary_to_bytes(small_vocab))
    data[100] ^= 0xFF
    path = tmp_path / "bad.skvoc"
    path.write_bytes(bytes(data))
    with pytest.raises(DatasetError, match=r"bad\.skvoc: checksum mismatch"):
        load_vocabulary(path)
    path.write_bytes(b"hello world, not a vocabulary")
    with pytest.raises(DatasetError, match="unknown vocabulary format"):
        load_vocabulary(path)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("10 6 0\n", r"voc\.txt:1: expected the header"),
        ("30 6  0 0\n" + f"0 1 {_row(1)}  1\n", r"voc\.txt:1: header .* out of range"),
        ("2 1  0 0\n" + f"0 1 {_row(1)}  1\n" + f"0 1 {_row(2)}\n", r"voc\.txt:3: expected 35 values .* got 34"),
        ("2 1  0 0\n" + f"0 1 {_row(1)}  1\n" + f"5 1 {_row(2)}  1\n", r"voc\.txt:3: parent id must be smaller"),
        ("2 1  0 0\n" + f"0 1 {_row(1)}  1\n" + f"0 2 {_row(2)}  1\n", r"voc\.txt:3: is_leaf must be 0 or 1"),
        ("2 1  0 0\n" + f"0 1 {_row(300)}  1\n", r"voc\.txt:2: descriptor bytes must be in \[0, 255\]"),
        ("2 1  0 0\n" + f"0 1 {_row(1)}  abc\n", r"voc\.txt:2: 'abc' is not a number"),
        ("2 1  0 0\n" + f"0 1 {_row(1)}  -1\n", r"voc\.txt:2: weight must be"),
        ("2 1  0 0\n" + f"0 0 {_row(1)}  0\n", r"node 1 is not a leaf but has no children"),
        ("2 1  0 0\n\n", r"no node after its header"),
    ],
)
def test_malformed_text_names_file_and_line(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "voc.txt"
    path.write_text(text)
    with pytest.raises(DatasetError, match=match):
        read_text_vocabulary(path)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match=r"nope\.txt: vocabulary file not found"):
        load_vocabulary(tmp_path / "nope.txt")
