"""Map export of a real run (issue 18.3 "done when"): the synthetic room run sequentially in-process, its map
exported; the PLY read with plyfile has as many points as the map, the COLMAP model loads with pycolmap, its camera
centres match the run's keyframes.tum, and COLMAP's own projection puts the points on their features. The default
suite runs the room's first 1.5 s; the whole room (with its loop closed) is the slow variant."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from omegaconf import OmegaConf

import slamkit.export.cli as export_cli
from slamkit.app import build_runner
from slamkit.cli import main
from slamkit.config import compose_config
from slamkit.export import export_map
from slamkit.export.colours import NO_COLOUR_RGB, DatasetImages, dataset_for_colours
from slamkit.io.trajectory_io import read_trajectory
from slamkit.map.atlas import Atlas

plyfile = pytest.importorskip("plyfile", reason="plyfile (dev extra) reads the PLY back")
pycolmap = pytest.importorskip("pycolmap", reason="pycolmap (dev extra) reads the COLMAP model back")

#: The default suite's run: the room's first 45 frames (initialised at frame 10; 8 keyframes, ~760 points).
SHORT = ["dataset.max_frames=45"]


def run_room(run_dir: Path, overrides: list[str]) -> tuple[Atlas, dict[str, Any]]:
    """The room run sequentially with a run directory (keyframes.tum, config.yaml); its Atlas and resolved config."""
    cfg = compose_config(["runner=sequential", "runner.progress=false", *overrides])
    runner, dataset = build_runner(cfg)
    config = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(config, dict)
    runner.run(dataset, dataset.camera, run_dir=run_dir, config={str(k): v for k, v in config.items()})
    return runner.atlas, {str(k): v for k, v in config.items()}


@pytest.fixture(scope="module")
def short_room(tmp_path_factory: pytest.TempPathFactory) -> tuple[Atlas, dict[str, Any], Path]:
    run_dir = tmp_path_factory.mktemp("room") / "run"
    atlas, config = run_room(run_dir, SHORT)
    return atlas, config, run_dir


def check_export(atlas: Atlas, config: dict[str, Any], run_dir: Path, out: Path) -> None:
    """The acceptance checks of the PLY and COLMAP exports of a run's Atlas."""
    images = DatasetImages(dataset_for_colours(config))
    store = atlas.active
    assert len(atlas) == 1 and store.n_keyframes() >= 3 and store.n_points() >= 100

    export_map(atlas, "ply", out / "map.ply", colours=images)
    v = plyfile.PlyData.read(str(out / "map.ply"))["vertex"]
    assert len(v) == store.n_points()
    assert np.array_equal(np.asarray(v["point_id"]), np.array(store.point_ids()))
    rgb = np.column_stack([v["red"], v["green"], v["blue"]])
    # the room's textures are coloured: the colours come from the images (not the no-colour grey, not grey levels)
    assert not (rgb == NO_COLOUR_RGB).all(axis=1).any()
    assert np.mean((rgb.max(axis=1) - rgb.min(axis=1)) > 10) > 0.5

    export_map(atlas, "colmap", out / "sparse", colours=images)
    rec = pycolmap.Reconstruction(str(out / "sparse"))
    assert len(rec.images) == store.n_keyframes() and len(rec.points3D) == store.n_points()
    # camera centres: the run's keyframes.tum (time order = keyframe id order)
    tum = read_trajectory(run_dir / "keyframes.tum", "tum")
    centres = np.stack([rec.images[i].projection_center() for i in sorted(rec.images)])
    np.testing.assert_allclose(centres, tum.T_w_c[:, :3, 3], rtol=0, atol=1e-9)
    # COLMAP's own projection of each point lands on its features (ORB-SLAM's chi-square gate at level 0 allows
    # sqrt(5.991) = 2.4 px; the features of higher levels more)
    errors = []
    for point in rec.points3D.values():
        for el in point.track.elements:
            image = rec.images[el.image_id]
            uv = image.camera.img_from_cam((image.cam_from_world() * point.xyz).reshape(1, 3)).reshape(2)
            errors.append(np.linalg.norm(uv - image.points2D[el.point2D_idx].xy))
    assert np.median(errors) < 1.0 and np.percentile(errors, 90) < 3.0
    assert np.mean([p.error for p in rec.points3D.values()]) == pytest.approx(np.mean(errors), rel=0.5)


def test_room_export(short_room: tuple[Atlas, dict[str, Any], Path], tmp_path: Path) -> None:
    atlas, config, run_dir = short_room
    check_export(atlas, config, run_dir, tmp_path)


def test_slamkit_export_of_the_run_directory(
    short_room: tuple[Atlas, dict[str, Any], Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The command on the run directory: colours and keyframe images from the run's config.yaml (the map file's
    reader, issue 17.3, stands in as the run's Atlas)."""
    atlas, _, run_dir = short_room
    (run_dir / export_cli.MAP_FILE_NAMES[0]).write_bytes(b"stand-in")
    monkeypatch.setattr(export_cli, "read_map_file", lambda path: (atlas, None))
    args = ["export", str(run_dir), "--format", "colmap", "--out", str(tmp_path / "sparse" / "0")]
    assert main([*args, "--images", str(tmp_path / "images")]) == 0
    rec = pycolmap.Reconstruction(str(tmp_path / "sparse" / "0"))
    assert sorted(p.name for p in (tmp_path / "images").iterdir()) == sorted(im.name for im in rec.images.values())
    assert not any(tuple(p.color) == NO_COLOUR_RGB for p in rec.points3D.values())
    assert main(["export", str(run_dir), "--format", "tum", "--out", str(tmp_path / "kf.tum")]) == 0
    assert (tmp_path / "kf.tum").read_text() == (run_dir / "keyframes.tum").read_text()


@pytest.mark.slow
@pytest.mark.timeout(3 * 3600)
def test_whole_room_export_after_its_loop(tmp_path: Path) -> None:
    atlas, config = run_room(tmp_path / "run", [])
    check_export(atlas, config, tmp_path / "run", tmp_path / "out")


def test_slamkit_export_of_a_saved_map_file(short_room: tuple[Atlas, dict[str, Any], Path], tmp_path: Path) -> None:
    """With the map file format of issue 17.3: the run's Atlas saved, then exported from the file by the command."""
    mapfile = pytest.importorskip("slamkit.map.mapfile", reason="map files (issue 17.3) are not in this version")
    atlas, config, _ = short_room
    path = tmp_path / "room.slamkit"
    mapfile.save_atlas(atlas, path, config)
    assert main(["export", str(path), "--format", "ply", "--out", str(tmp_path / "map.ply")]) == 0
    v = plyfile.PlyData.read(str(tmp_path / "map.ply"))["vertex"]
    assert np.array_equal(np.asarray(v["point_id"]), np.array(atlas.active.point_ids()))
    assert not any((r, g, b) == NO_COLOUR_RGB for r, g, b in zip(v["red"], v["green"], v["blue"], strict=True))
