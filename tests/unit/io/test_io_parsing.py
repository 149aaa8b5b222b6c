"""Shared parsing helpers: text tables, images, association, IMU windows (trajectory files: test_io_trajectory)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from slamkit.errors import CalibrationError, DatasetError
from slamkit.io.images import load_depth, load_image
from slamkit.io.textfiles import (
    read_numeric_table,
    read_stamped_files,
    times_from_names,
)
from slamkit.io.timing import associate_stamps, imu_between
from slamkit.sensors import ImuSamples


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_numeric_table_skips_comments_and_keeps_line_numbers(tmp_path: Path) -> None:
    p = _write(tmp_path / "t.txt", "# header\n\n1 2\n# mid\n3 4\n")
    table = read_numeric_table(p, 2)
    np.testing.assert_array_equal(table.values, [[1, 2], [3, 4]])
    np.testing.assert_array_equal(table.lines, [3, 5])


def test_wrong_column_count_names_file_and_line(tmp_path: Path) -> None:
    p = _write(tmp_path / "t.txt", "1 2\n3 4 5\n")
    with pytest.raises(DatasetError, match=r"t\.txt:2: expected 2 columns .*got 3"):
        read_numeric_table(p, 2)


def test_non_numeric_field_names_file_line_and_column(tmp_path: Path) -> None:
    p = _write(tmp_path / "t.txt", "1 2\n3 x4\n")
    with pytest.raises(DatasetError, match=r"t\.txt:2: column 2 should be a number .*'x4'"):
        read_numeric_table(p, 2)


def test_non_finite_field_is_rejected(tmp_path: Path) -> None:
    p = _write(tmp_path / "t.txt", "1 nan\n")
    with pytest.raises(DatasetError, match=r"t\.txt:1: column 2 should be finite"):
        read_numeric_table(p, 2)


def test_missing_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match=r"nope\.txt does not exist"):
        read_numeric_table(tmp_path / "nope.txt", 2)


def test_stamped_list_rejects_time_going_back(tmp_path: Path) -> None:
    p = _write(tmp_path / "rgb.txt", "# c\n1.0 a.png\n2.0 b.png\n1.5 c.png\n")
    with pytest.raises(DatasetError, match=r"rgb\.txt:4: .*strictly increasing; 1\.5 follows 2\.0 on line 3"):
        read_stamped_files(p, tmp_path, sep=None, ns_stamps=False, what="rgb")


def test_stamped_list_ns_stamps_keep_float64_precision(tmp_path: Path) -> None:
    p = _write(tmp_path / "data.csv", "#t,f\n1403715273262142976,a.png\n1403715273312143104,b.png\n")
    files = read_stamped_files(p, tmp_path, sep=",", ns_stamps=True, what="cam0")
    assert files.t_s[0] == pytest.approx(1403715273.262142976, abs=1e-7)
    # float64 resolves ~2.4e-7 s at 1.4e9 s; a naive float(ns) * 1e-9 would be off by up to ~1e-7 more.
    assert files.t_s[1] - files.t_s[0] == pytest.approx(0.050000128, abs=5e-7)
    assert files.files[1] == tmp_path / "b.png"


def test_stamped_list_missing_image_names_list_line(tmp_path: Path) -> None:
    p = _write(tmp_path / "rgb.txt", "1.0 rgb/a.png\n")
    files = read_stamped_files(p, tmp_path, sep=None, ns_stamps=False, what="rgb")
    with pytest.raises(DatasetError, match=r"rgb\.txt:1: image file .*a\.png listed there does not exist"):
        files.check_files_exist()


def test_times_from_names(tmp_path: Path) -> None:
    names = [tmp_path / "1305031102.175304.png", tmp_path / "1305031102.211214.png"]
    np.testing.assert_allclose(times_from_names(names, 1.0, "x"), [1305031102.175304, 1305031102.211214])
    ns = [tmp_path / "1403715273262142976.png"]
    assert times_from_names(ns, 1e-9, "x")[0] == pytest.approx(1403715273.262142976, abs=1e-7)
    with pytest.raises(DatasetError, match=r"frame_a\.png: .*should be a number"):
        times_from_names([tmp_path / "frame_a.png"], 1.0, "x")


def test_associate_matches_tum_greedy_rule() -> None:
    # Greedy by |dt|: (1.00, 1.005) first, then 1.03 cannot take 1.005 again and takes 1.045 (dt 0.015);
    # 1.06 has no partner left within 0.02.
    t_a = np.array([1.00, 1.03, 1.06])
    t_b = np.array([1.005, 1.045, 1.2])
    ia, ib = associate_stamps(t_a, t_b, 0.02)
    np.testing.assert_array_equal(ia, [0, 1])
    np.testing.assert_array_equal(ib, [0, 1])


def test_imu_between_is_half_open() -> None:
    t = np.array([0.0, 0.1, 0.2, 0.3])
    imu = ImuSamples(t, np.arange(12.0).reshape(4, 3), -np.arange(12.0).reshape(4, 3))
    w = imu_between(imu, 0.1, 0.3)
    np.testing.assert_array_equal(w.t_s, [0.2, 0.3])
    np.testing.assert_array_equal(w.acc_mps2[0], [6, 7, 8])


def test_load_image_errors(tmp_path: Path) -> None:
    img = (np.arange(40 * 30) % 251).astype(np.uint8).reshape(30, 40)
    good = tmp_path / "good.png"
    cv2.imwrite(str(good), img)
    np.testing.assert_array_equal(load_image(good).grey, img)
    with pytest.raises(CalibrationError, match=r"good\.png is 40x30 px but the calibration \(calib\.yaml\) is 640x480"):
        load_image(good, (640, 480), "calib.yaml")
    truncated = tmp_path / "trunc.png"
    truncated.write_bytes(good.read_bytes()[:60])
    with pytest.raises(DatasetError, match=r"trunc\.png could not be decoded"):
        load_image(truncated)
    with pytest.raises(DatasetError, match=r"absent\.png does not exist"):
        load_image(tmp_path / "absent.png")


def test_load_depth_scales_to_metres(tmp_path: Path) -> None:
    raw = np.array([[0, 5000], [10000, 65535]], dtype=np.uint16)
    p = tmp_path / "d.png"
    cv2.imwrite(str(p), raw)
    depth = load_depth(p, 5000.0)
    assert depth.dtype == np.float32
    np.testing.assert_allclose(depth, [[0.0, 1.0], [2.0, 13.107]], rtol=1e-6)
    grey = tmp_path / "g.png"
    cv2.imwrite(str(grey), np.zeros((2, 2, 3), np.uint8))
    with pytest.raises(DatasetError, match=r"depth file .*g\.png .*expected a one-channel 16-bit"):
        load_depth(grey, 5000.0)
