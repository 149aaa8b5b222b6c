"""Saved maps end to end (issue 17 items 3 and 6) on a real map: the synthetic room run sequentially in-process for 300
frames, saved and read back exactly; then a second run of the room from frame 790 (where the camera is back over
what frames 0.. mapped) with ``map.load=``: its first frame relocalizes in the loaded map, it tracks and relocalizes
exactly as the same run does on the map kept in memory, and its ATE is good; ``slamkit run map.save=`` writes the
map (also when the run fails late)."""

from __future__ import annotations

import functools
import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from omegaconf import OmegaConf

from slamkit.app import build_runner
from slamkit.config import compose_config
from slamkit.eval.metrics import compute_ate
from slamkit.io.trajectory_io import read_trajectory
from slamkit.map import mapfile_run
from slamkit.map.atlas import Atlas
from slamkit.map.mapfile import load_atlas, map_file_info, save_atlas
from slamkit.map.mapfile_contents import differences, read_map_contents
from slamkit.pipeline.tracking import TrackingState
from slamkit.pipeline.trajectory import TrajectoryRecorder
from slamkit.plugins import ComponentRegistry

pytestmark = pytest.mark.timeout(900)

FIRST = ["runner=sequential", "runner.progress=false", "dataset.max_frames=300"]
# frames 790..: the room's trajectory is back over its start (tests/integration/test_relocalization.py)
SECOND = ["runner=sequential", "runner.progress=false", "dataset.skip=[0,789]"]


@functools.cache
def _first_run() -> tuple[Any, dict[str, Any]]:
    cfg = compose_config(FIRST)
    runner, dataset = build_runner(cfg)
    runner.run(dataset, dataset.camera)
    config = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(config, dict)
    return runner, {str(k): v for k, v in config.items()}


@pytest.fixture(scope="module")
def room(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Any, Path]]:
    """The room's 300-frame run and its map saved to a file."""
    runner, config = _first_run()
    path = tmp_path_factory.mktemp("maps") / "room.slamkit"
    save_atlas(runner.atlas, path, config, runner.map_frames())
    yield runner, path


def _new_store_and_place(overrides: list[str]) -> tuple[Any, Any]:
    cfg = compose_config(overrides)
    registry = ComponentRegistry.discover()
    place = registry.instantiate("place", cfg.place)
    node = mapfile_run.store_node(cfg.map)
    return (lambda ids: registry.instantiate("map", node, ids=ids)), place


@pytest.mark.slow  # the 300-frame room run: ~2 min under load (the default suite has test_slamkit_run_saves_and_loads_a_map)
def test_a_real_room_map_round_trips_exactly(room: tuple[Any, Path]) -> None:
    runner, path = room
    atlas: Atlas = runner.atlas
    active = atlas.active
    assert active.n_keyframes() >= 15 and active.n_points() >= 1000 and active.covisibility.edges()
    new_store, place = _new_store_and_place(FIRST)
    loaded = load_atlas(path, new_store, place)
    assert loaded.map_ids() == atlas.map_ids() and loaded.active_id == atlas.active_id
    assert loaded.ids.next_ids() == atlas.ids.next_ids()
    for map_id, store in atlas.items():
        # ids, poses, features, point_ids, bags of words, points, descriptors, counters, graphs: bit for bit
        assert not differences(read_map_contents(store), read_map_contents(loaded.get(map_id))), map_id
    assert sorted(place.database.keyframe_ids()) == sorted(runner.tracker.place.database.keyframe_ids())
    info = map_file_info(path)
    assert info.n_keyframes == sum(s.n_keyframes() for _, s in atlas.items())
    assert info.size_bytes == path.stat().st_size
    # the run's frames (each relative to a keyframe of the map, culled references resolved) come back bit for bit,
    # and placed against the loaded keyframes they are the run's trajectory
    frames = runner.map_frames()[atlas.active_id]
    back = loaded.loaded_frames[atlas.active_id]
    assert info.n_frames == len(back) == len(frames) == len(runner.recorder)
    for name in ("t_s", "frame_index", "ref_kf_id", "T_c_r"):
        np.testing.assert_array_equal(getattr(back, name), getattr(frames, name))
    replayed = TrajectoryRecorder()
    replayed.load(back)
    trajectory = runner.recorder.frames(active)
    np.testing.assert_array_equal(replayed.frames(loaded.active).t_s, trajectory.t_s)
    np.testing.assert_allclose(replayed.frames(loaded.active).T_w_c, trajectory.T_w_c, atol=1e-9)


def _second_run(atlas_source: str, path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[Any, Any]:
    """The room from frame 790 on the saved map ("file") or on the first run's map in memory ("memory")."""
    cfg = compose_config([*SECOND, f"map.load={path}"])
    if atlas_source == "memory":
        first, _ = _first_run()

        def in_memory(map_node: Any, new_store: Any, place: Any, cameras: Any) -> Atlas:
            atlas: Atlas = first.atlas
            atlas.place = place  # the second run's keyframe database, filled as a load fills it
            for _, store in atlas.items():
                for kf_id in store.keyframe_ids():
                    bow = store.get_keyframe(kf_id).bow
                    if bow is not None:
                        place.add(kf_id, bow)
            return atlas

        monkeypatch.setattr(mapfile_run, "run_atlas", in_memory)
    runner, dataset = build_runner(cfg)
    monkeypatch.undo()
    return runner, dataset


@pytest.mark.slow
def test_a_loaded_map_relocalizes_and_tracks_as_the_map_in_memory(
    room: tuple[Any, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    _, path = room
    with open(path, "rb") as f:
        before = f.read()
    runs = {}
    for source in ("file", "memory"):  # memory last: it goes on changing the first run's Atlas
        runner, dataset = _second_run(source, path, monkeypatch)
        runner.run(dataset, dataset.camera)
        runs[source] = (runner, dataset)
    runner, dataset = runs["file"]
    outcomes = runner.log.tracking
    assert outcomes[0].state == TrackingState.OK and outcomes[0].method == "relocalization"
    assert all(o.state == TrackingState.OK for o in outcomes), "every frame tracked on the loaded map"
    assert runner.atlas.map_ids() == [0] and runner.log.new_maps == 0
    # the same relocalization and tracking, bit for bit, as on the map kept in memory
    memory = runs["memory"][0].log.tracking
    assert [o.method for o in outcomes] == [o.method for o in memory]
    for a, b in zip(outcomes, memory, strict=True):
        assert a.T_c_w is not None and b.T_c_w is not None
        np.testing.assert_array_equal(a.T_c_w, b.T_c_w)
    # the poses, in the loaded map's frame, against the truth
    gt = dataset.ground_truth
    assert gt is not None
    ate = compute_ate(gt, runner.recorder.frames(runner.store), align="sim3")
    assert ate.rmse_m < 0.02, ate.rmse_m
    assert path.read_bytes() == before, "loading never writes the file"


def _slamkit(cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "slamkit", *args], cwd=cwd, capture_output=True, text=True, timeout=600, check=False
    )


def test_slamkit_run_saves_and_loads_a_map(tmp_path: Path) -> None:
    """``slamkit run map.save=true`` (map.slamkit in the run directory), ``map.load=`` with ``map.save=`` elsewhere,
    ``slamkit map info``, and a bad file given to ``map.load``: one line naming it, exit 2."""
    quick = ["runner=sequential", "runner.progress=false"]
    run1 = tmp_path / "run1"
    result = _slamkit(tmp_path, "run", *quick, "dataset.max_frames=60", "map.save=true", f"hydra.run.dir={run1}")
    assert result.returncode == 0, result.stderr
    saved = run1 / "map.slamkit"
    info = map_file_info(saved)
    assert info.n_keyframes >= 2
    first = read_trajectory(run1 / "trajectory.tum", "tum")
    assert info.n_frames == len(first) >= 40, "the run's frames are in the file"
    # frames 40..59 again on the loaded map, saved to another file: relocalized in it, the map kept and extended
    again = tmp_path / "again.slamkit"
    later = [*quick, "dataset.skip=[0,39]", "dataset.max_frames=20"]
    result = _slamkit(tmp_path, "run", *later, f"map.load={saved}", f"map.save={again}", f"hydra.run.dir={tmp_path}/r2")
    assert result.returncode == 0, result.stderr
    assert map_file_info(again).n_keyframes >= info.n_keyframes
    metrics = json.loads((tmp_path / "r2" / "metrics.json").read_text())
    assert metrics["frames_tracked"] == 20, "every frame tracked on the loaded map"
    # the second run's trajectory.tum: both sessions' frames (metrics.json counts its own); its map file keeps them
    both = read_trajectory(tmp_path / "r2" / "trajectory.tum", "tum")
    assert len(both) == len(first) + 20 and np.all(np.diff(both.t_s) >= 0)
    assert map_file_info(again).n_frames == len(both)
    shown = _slamkit(tmp_path, "map", "info", str(again))
    assert shown.returncode == 0 and "schema version  1" in shown.stdout
    bad = tmp_path / "bad.slamkit"
    bad.write_bytes(saved.read_bytes()[:1000])
    result = _slamkit(tmp_path, "run", *later, f"map.load={bad}", f"hydra.run.dir={tmp_path}/r3")
    assert result.returncode == 2
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith("slamkit run: map file ") and str(bad) in last and "truncated" in last
