"""The Atlas end to end (issue 13): a camera that jumps to ground it has not mapped loses tracking, relocalization
fails for ORB-SLAM3's 3 s, and a new map starts while the old one stays; the run directory holds each map's
keyframes and trajectory and metrics.json a ``maps`` list; relocalization tries the active map only."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from slamkit.app import build_runner
from slamkit.config import compose_config
from slamkit.io.trajectory_io import read_trajectory
from slamkit.pipeline.tracking import TrackingState

# the room: frames 0..149 map one corner; the jump lands on frames 451.. looking at walls not mapped yet
pytestmark = pytest.mark.timeout(900)

ROOM_JUMP = ["runner=sequential", "runner.progress=false", "dataset.skip=[150,450]", "dataset.max_frames=360"]


def _check_run_directory(run_dir: Path, metrics: dict, n_maps: int) -> None:
    maps = metrics["maps"]
    assert [m["id"] for m in maps] == sorted(m["id"] for m in maps) and len(maps) == n_maps
    for entry in maps:
        map_dir = run_dir / "maps" / str(entry["id"])
        frames = read_trajectory(map_dir / "trajectory.tum", "tum")
        keyframes = read_trajectory(map_dir / "keyframes.tum", "tum")
        assert len(frames) == entry["frames"] and len(keyframes) == entry["keyframes"] > 0
        assert (map_dir / "frames.csv").is_file()
        for key in ("ate_rmse_m", "kf_ate_rmse_m"):
            assert entry[key] is not None or entry[key.replace("rmse_m", "error")]
    # the top-level trajectory is the biggest map's (ORB-SLAM3 SaveTrajectoryEuRoC)
    biggest = max(maps, key=lambda m: (m["keyframes"], -m["id"]))
    top = (run_dir / "trajectory.tum").read_text()
    assert top == (run_dir / "maps" / str(biggest["id"]) / "trajectory.tum").read_text()
    assert metrics["keyframes"] == biggest["keyframes"] and metrics["map_points"] == biggest["points"]


def test_a_jump_to_unmapped_ground_starts_a_second_map_and_keeps_the_first(tmp_path: Path) -> None:
    cfg = compose_config(ROOM_JUMP)
    runner, dataset = build_runner(cfg)
    config = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(config, dict)
    log = runner.run(dataset, dataset.camera, run_dir=tmp_path, config={str(k): v for k, v in config.items()})
    atlas = runner.atlas
    assert atlas.map_ids() == [0, 1] and atlas.active_id == 1
    assert log.new_maps == 1 and log.resets == 0
    first, second = atlas.get(0), atlas.get(1)
    assert first.n_keyframes() > 10 and second.n_keyframes() >= 2
    assert not set(first.keyframe_ids()) & set(second.keyframe_ids())
    assert not set(first.point_ids()) & set(second.point_ids())
    # lost at the jump; relocalization tried for 3 s of sequence time before the new map
    jump = next(i for i, o in enumerate(log.tracking) if o.frame_index == 150)
    new_map = next(i for i, o in enumerate(log.tracking) if "a new map starts" in o.message)
    assert log.tracking[jump].state == TrackingState.LOST
    assert all(o.state == TrackingState.LOST and o.method == "relocalization" for o in log.tracking[jump + 1 : new_map])
    lost_for_s = log.tracking[new_map].timestamp_s - log.tracking[jump].timestamp_s
    assert 3.0 - 1e-9 < lost_for_s < 3.0 + 1.5 / 30  # the first frame lost for more than 3 s

    # the run directory: each map's keyframes and trajectory, metrics.json's maps
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    _check_run_directory(tmp_path, metrics, 2)
    assert [m["keyframes"] for m in metrics["maps"]] == [first.n_keyframes(), second.n_keyframes()]
    assert metrics["maps"][0]["ate_rmse_m"] < 0.05

    # relocalization considers the active map only: a frame of the first map's ground has candidates there in the
    # keyframe database (one across maps), and tracking, lost in the second map, does not relocalize with them
    place, tracker = runner.tracker.place, runner.tracker
    assert place is not None
    frame = dataset[100]
    bow = place.transform(tracker.frontend.observe(frame, dataset.camera, False).descriptors)
    candidates = [k for k, _ in place.relocalization_candidates(bow, atlas.best_neighbors)]
    assert candidates and {atlas.map_of(k) for k in candidates} == {0}
    tracker.state = TrackingState.LOST
    out = tracker.step(frame, dataset.camera)
    assert out.method == "relocalization" and out.state != TrackingState.OK
    assert atlas.get(0).keyframe_ids() == first.keyframe_ids(), "the first map is kept as it was"


#: frame ATE (Sim3) of the uninterrupted long loop, `slamkit run runner=sequential runner.progress=false
#: dataset.scene=long_loop`, seed 0, loop closing with global BA after the loop (the default since 0996462), main
#: 9452f51: 2.89 cm (keyframes 2.74 cm). 2.38 cm at 85e6d2f before 83e454e's monocular defaults (initial-map culling,
#: record_reference=tracked); docs/BENCHMARKS.md "The uninterrupted long loop's 2.38 -> 2.89 cm traced"
LONG_LOOP_ATE_M = 0.0289


@pytest.mark.slow
@pytest.mark.timeout(3 * 3600)
@pytest.mark.parametrize("runner", ["sequential", "threaded"])
def test_long_loop_with_a_jump_makes_two_maps_then_merges_them(tmp_path: Path, runner: str) -> None:
    """Issue 17's acceptance run: ``slamkit run dataset.scene=long_loop "dataset.skip=[700,1500]"``: the jump lands
    where the first map never went, so a second map starts; back on the first map's ground, the two are merged
    (ORB-SLAM3 map merging) and the whole run's trajectory, in one frame, is within 1.5x of the uninterrupted run's
    ATE."""
    run_dir = tmp_path / "run"
    cmd = [
        sys.executable,
        "-m",
        "slamkit",
        "run",
        f"runner={runner}",
        "dataset.scene=long_loop",
        "dataset.skip=[700,1500]",
        "runner.progress=false",
        f"hydra.run.dir={run_dir}",
    ]
    subprocess.run(cmd, check=True, capture_output=True, timeout=3 * 3600)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["maps_merged"] >= 1
    _check_run_directory(run_dir, metrics, len(metrics["maps"]))
    assert len(metrics["maps"]) == 1
    assert metrics["loops_false"] == 0
    assert metrics["ate_rmse_m"] < 1.5 * LONG_LOOP_ATE_M


@pytest.mark.slow  # 40 s: the default suite keeps the sequential jump above; this one is run with -m slow
def test_the_threaded_runner_starts_the_second_map_with_its_workers_parked(tmp_path: Path) -> None:
    """Same jump with ORB-SLAM's three threads: local mapping and loop closing are parked and their queues
    dropped while the active map changes; the first map is kept and the run directory lists both."""
    cfg = compose_config(["runner=threaded", *ROOM_JUMP[1:]])
    runner, dataset = build_runner(cfg)
    log = runner.run(dataset, dataset.camera, run_dir=tmp_path, config={"seed": 0})
    atlas = runner.atlas
    assert atlas.map_ids() == [0, 1] and log.new_maps == 1
    first, second = atlas.get(0), atlas.get(1)
    assert first.n_keyframes() > 10
    assert not set(first.keyframe_ids()) & set(second.keyframe_ids())
    assert not set(first.point_ids()) & set(second.point_ids())
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert [(m["id"], m["keyframes"]) for m in metrics["maps"]] == [
        (0, first.n_keyframes()),
        (1, second.n_keyframes()),
    ]
    assert (tmp_path / "maps" / "0" / "trajectory.tum").is_file() and (tmp_path / "maps" / "1").is_dir()
