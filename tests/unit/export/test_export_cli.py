"""``slamkit export``: SOURCE resolution and its errors (one line, exit 2), the files written. The map-file reader
(issue 17.3) is replaced here by a hand-made map; tests/integration/test_export_room.py exports a real run."""

from __future__ import annotations

from pathlib import Path

import pytest
from export_maps import PINHOLE, build_map

import slamkit.export.cli as export_cli
from slamkit.cli import main
from slamkit.io.trajectory_io import read_trajectory
from slamkit.map.atlas import Atlas
from slamkit.map.store import InMemoryMapStore

plyfile = pytest.importorskip("plyfile", reason="plyfile (dev extra) reads the PLY back")


@pytest.fixture
def run_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A run directory holding a map file, read as a hand-made map of 60 points."""
    store = InMemoryMapStore()
    build_map(PINHOLE, store)
    run = tmp_path / "run"
    run.mkdir()
    (run / export_cli.MAP_FILE_NAMES[0]).write_bytes(b"stand-in")
    monkeypatch.setattr(export_cli, "read_map_file", lambda path: (Atlas.of(store), None))
    return run


def test_export_a_run_directory_as_ply_and_tum(run_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["export", str(run_dir), "--format", "ply", "--out", str(run_dir / "map.ply")]) == 0
    out, err = capsys.readouterr()
    assert "map 0: 3 keyframes, 60 points" in out
    assert "no run config" in err  # no config.yaml: no images to take colours from, said so
    assert len(plyfile.PlyData.read(str(run_dir / "map.ply"))["vertex"]) == 60
    assert main(["export", str(run_dir), "--format", "tum", "--out", str(run_dir / "kf.tum")]) == 0
    assert len(read_trajectory(run_dir / "kf.tum", "tum")) == 3


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["nowhere"], "nowhere: no such map file or run directory"),
        (["EMPTY"], "no map file in this run directory"),
        (["RUN", "--map", "4"], "map 4 is not in the Atlas"),
    ],
)
def test_errors_are_one_line_and_exit_2(
    run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    (tmp_path / "EMPTY").mkdir()
    source = {"RUN": str(run_dir), "EMPTY": str(tmp_path / "EMPTY")}.get(args[0], str(tmp_path / args[0]))
    code = main(["export", source, *args[1:], "--format", "ply", "--out", str(tmp_path / "x.ply")])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("slamkit export: ") and message in err and err.count("\n") == 1
    assert not (tmp_path / "x.ply").exists()


def test_a_map_file_that_is_not_one_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "map.slamkit"
    path.write_bytes(b"")
    assert main(["export", str(tmp_path), "--format", "ply", "--out", str(tmp_path / "x.ply")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("slamkit export: ") and str(path) in err and err.count("\n") == 1
    assert not (tmp_path / "x.ply").exists()
