"""Multi-session mapping (issue 17 item 5; docs/atlas.md, "Multi-session"): ``slamkit run map.load=A`` on a second
sequence goes on mapping in the same Atlas. ``map.session_start``: ``new_map`` (ORB-SLAM3 System::LoadAtlas then
Atlas::CreateNewMap) starts a new map for the session, which map merging joins to the loaded one when the camera
revisits its ground, so both sessions' trajectories end in the loaded map's frame; ``reloc_or_new_map`` (default)
goes on in the loaded map when a frame relocalizes in it while the new map is being initialised.

The room's camera circles it once in 24 s (720 frames) then passes its start again: the first session maps frames
0..N-1, the second starts at frame N, over ground the first session saw last."""

from __future__ import annotations

import functools
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from omegaconf import OmegaConf

from slamkit.app import build_runner
from slamkit.config import compose_config
from slamkit.eval.metrics import compute_ate
from slamkit.io.trajectory_io import read_trajectory
from slamkit.map.mapfile import map_file_info, save_atlas
from slamkit.pipeline.tracking import TrackingState
from slamkit.sensors import Trajectory

pytestmark = pytest.mark.timeout(1800)

#: frame ATE (Sim3) of the uninterrupted room run, sequential, seed 0, with global BA after the loop (the default
#: since 0996462; docs/BENCHMARKS.md, real footage after the session-10 merges: 0.82 cm; 1.07 cm before)
ROOM_ATE_M = 0.0082
ROOM_KF_ATE_M = 0.0081  # keyframes of the same run
HALF = 420  # the whole room is 840 frames


@functools.cache
def _first_session(n_frames: int, tmp: str) -> tuple[Path, Path]:
    """The room's frames 0..n_frames-1 run sequentially and saved (what ``map.save`` writes): (the map file, the run
    directory)."""
    run_dir = Path(tmp) / f"first{n_frames}"
    path = Path(tmp) / f"room{n_frames}.slamkit"
    runner, _, config = _run(["runner=sequential", f"dataset.max_frames={n_frames}"], run_dir)
    save_atlas(runner.atlas, path, config, runner.map_frames())
    return path, run_dir


def _run(overrides: list[str], run_dir: Path) -> tuple[Any, Any, dict[str, Any]]:
    cfg = compose_config(["runner.progress=false", *overrides])
    runner, dataset = build_runner(cfg)
    resolved = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(resolved, dict)
    config = {str(k): v for k, v in resolved.items()}
    runner.run(dataset, dataset.camera, run_dir=run_dir, config=config)
    return runner, dataset, config


def _joined(*trajectories: Trajectory) -> Trajectory:
    t = np.concatenate([tr.t_s for tr in trajectories])
    order = np.argsort(t, kind="stable")
    return Trajectory(t[order], np.concatenate([tr.T_w_c for tr in trajectories])[order])


def _after(traj: Trajectory, t_s: float) -> Trajectory:
    """The frames of ``traj`` later than ``t_s`` (the second session's: after the first session's last frame)."""
    keep = traj.t_s > t_s + 1e-6
    return Trajectory(traj.t_s[keep], traj.T_w_c[keep])


def _second_session(
    first: Path, start: int, session_start: str, runner: str, run_dir: Path, save: Path | None = None, *extra: str
) -> tuple[Any, Any]:
    """The room from frame ``start`` on, a session on the map file ``first`` (saved to ``save`` at the end)."""
    overrides = [f"runner={runner}", f"dataset.skip=[0,{start - 1}]", f"map.load={first}"]
    runner_, dataset, config = _run([*overrides, f"map.session_start={session_start}", *extra], run_dir)
    if save is not None:
        save_atlas(runner_.atlas, save, config, runner_.map_frames())
    return runner_, dataset


def test_a_second_session_starts_a_new_map_or_goes_on_in_the_loaded_one(
    tmp_path_factory: pytest.TempPathFactory,
) -> None:
    """Frames 0..39 mapped and saved; frames 40..54 as a second session: with ``new_map`` it initialises a map of its
    own and the loaded one stays in the Atlas untouched; with the default its first frame relocalizes in the loaded
    map, the session goes on in it (no new map) and its poses are in the first session's frame."""
    tmp = tmp_path_factory.mktemp("short")
    first, first_dir = _first_session(40, str(tmp))
    n_kfs = map_file_info(first).n_keyframes
    runner, _ = _second_session(first, 40, "new_map", "sequential", tmp / "new", None, "dataset.max_frames=15")
    atlas, log = runner.atlas, runner.log
    assert atlas.map_ids() == [0, 1] and atlas.active_id == 1 and log.new_maps == 1
    assert atlas.get(0).n_keyframes() == n_kfs, "the loaded map is kept as it was"
    assert runner.tracker.relocalizations == 0, "ORB-SLAM3: a new session never relocalizes in a loaded map"
    assert atlas.active.n_keyframes() >= 2 and log.tracking[-1].state == TrackingState.OK
    runner, dataset = _second_session(
        first, 40, "reloc_or_new_map", "sequential", tmp / "reloc", None, "dataset.max_frames=15"
    )
    atlas, log = runner.atlas, runner.log
    assert log.tracking[0].method == "relocalization" and log.tracking[0].state == TrackingState.OK
    assert atlas.map_ids() == [0] and log.new_maps == 0
    assert all(o.state == TrackingState.OK for o in log.tracking)
    # the second run's trajectory.tum holds both sessions' frames (the map file kept the first one's), with one
    # alignment: the second session's poses are in the first one's frame
    first_traj = read_trajectory(first_dir / "trajectory.tum", "tum")
    assert map_file_info(first).n_frames == len(first_traj)
    both = read_trajectory(tmp / "reloc" / "trajectory.tum", "tum")
    assert len(both) == len(first_traj) + 15 and np.all(np.diff(both.t_s) > 0)
    assert dataset.ground_truth is not None
    assert compute_ate(dataset.ground_truth, both, align="sim3").rmse_m < 0.01
    # the frames of the first session are where its own run put them (the second one changed its keyframes little)
    np.testing.assert_allclose(both.T_w_c[: len(first_traj), :3, 3], first_traj.T_w_c[:, :3, 3], atol=0.01)


@pytest.fixture(scope="module")
def first_half(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    return _first_session(HALF, str(tmp_path_factory.mktemp("halves")))


@pytest.mark.slow
@pytest.mark.parametrize("runner_name", ["sequential", "threaded"])
def test_the_room_in_two_sessions_merges_into_the_first_sessions_frame(
    first_half: tuple[Path, Path], runner_name: str, tmp_path: Path
) -> None:
    """The room's first half saved, the second half a new session on it with ORB-SLAM3's start (``new_map``): its
    map (initialised late: the first frames are twofold planar ambiguities) is merged with the loaded one when the
    camera comes back to the first session's start; the loaded map is absorbed with the first session's frames the
    file kept, so the second run's trajectory.tum holds both sessions' frames in the first run's frame (one Sim3
    alignment: centimetres, where separate frames would be off by metres), and the map saved after it holds both
    sessions' keyframes and frames. Measured (docs/BENCHMARKS.md, "Multi-session: the sessions' frames in the map
    file"): 1.36 cm sequential, 1.35-1.36 cm threaded (1.66x the single run), as the two sessions are welded at one
    end of the room only; issue 17's 1.5x is met by the default start (the test below)."""
    first, first_dir = first_half
    saved = tmp_path / "both.slamkit"
    runner, dataset = _second_session(first, HALF, "new_map", runner_name, tmp_path / "second", saved)
    log, atlas = runner.log, runner.atlas
    assert log.new_maps == 1 and log.maps_merged == 1
    assert len(atlas) == 1, "the loaded map was absorbed by the session's map"
    written = json.loads((tmp_path / "second" / "metrics.json").read_text())
    assert written["maps_merged"] == 1 and written["loops_false"] == 0
    merges = [lp for lp in log.loops if lp.merge_transform is not None]
    assert len(merges) == 1 and merges[0].merge_map_id == 0, "the loaded map (id 0) merged into the session's"
    gt = dataset.ground_truth
    assert gt is not None
    first_traj = read_trajectory(first_dir / "trajectory.tum", "tum")
    second_traj = read_trajectory(tmp_path / "second" / "trajectory.tum", "tum")  # both sessions' frames
    assert len(_after(second_traj, float(first_traj.t_s.max()))) >= 200
    assert len(second_traj) >= len(first_traj) + 200, "the absorbed loaded map's frames are in the merged map's"
    both = compute_ate(gt, second_traj, align="sim3")
    print(f"{runner_name}: two sessions together {both.rmse_m * 100:.2f} cm")
    assert both.rmse_m < 2.0 * ROOM_ATE_M, both.rmse_m
    info = map_file_info(saved)
    assert len(info.maps) == 1 and info.n_keyframes == atlas.active.n_keyframes()
    assert info.n_frames == len(second_traj), "the saved map keeps both sessions' frames, for a third session"
    assert info.n_keyframes > map_file_info(first).n_keyframes


@pytest.mark.slow
def test_the_room_in_two_sessions_by_default_goes_on_in_the_loaded_map(
    first_half: tuple[Path, Path], tmp_path: Path
) -> None:
    """Issue 17's multi-session acceptance with the default ``reloc_or_new_map``: the second half's first frame is
    over the first half's last ground, so it relocalizes there and the session maps on in the loaded map (the room's
    loop is closed in it at the end). The map file keeps the first session's frames (each relative to its reference
    keyframe), so the second run's trajectory.tum holds both sessions' frames placed against the keyframes as its
    loop correction and global BA left them: within 1.5x of a single run over the whole room (docs/BENCHMARKS.md,
    "Multi-session"; 1.55 cm = 1.89x when only the first run's own trajectory.tum had its frames, as it wrote them);
    the keyframes of both sessions in the map at the end within 1.5x of the single run's."""
    first, first_dir = first_half
    assert map_file_info(first).n_frames == len(read_trajectory(first_dir / "trajectory.tum", "tum"))
    runner, dataset = _second_session(first, HALF, "reloc_or_new_map", "sequential", tmp_path / "second")
    assert runner.log.new_maps == 0 and runner.atlas.map_ids() == [0]
    assert runner.log.tracking[0].method == "relocalization"
    gt = dataset.ground_truth
    assert gt is not None
    both = read_trajectory(tmp_path / "second" / "trajectory.tum", "tum")  # the second run's output alone
    assert len(both) >= 800 and both.t_s.min() < 1.0 and both.t_s.max() > 24.0, "both sessions' frames"
    together = compute_ate(gt, both, align="sim3").rmse_m
    first_traj = read_trajectory(first_dir / "trajectory.tum", "tum")
    second_only = _after(both, float(first_traj.t_s.max()))
    # the first run's frames as it wrote them with the second run's: what the runs gave before the map file kept frames
    as_written = compute_ate(gt, _joined(first_traj, second_only), align="sim3").rmse_m
    print(f"two sessions together {together * 100:.2f} cm (first run's frames as written: {as_written * 100:.2f} cm)")
    assert together < 1.5 * ROOM_ATE_M, together
    keyframes = read_trajectory(tmp_path / "second" / "keyframes.tum", "tum")
    assert keyframes.t_s.min() < 1.0 and keyframes.t_s.max() > 24.0, "both sessions' keyframes"
    assert compute_ate(gt, keyframes, align="sim3").rmse_m < 1.5 * ROOM_KF_ATE_M
    # metrics.json counts this run's frames (the second half), its ATE theirs against the ground truth
    written = json.loads((tmp_path / "second" / "metrics.json").read_text())
    assert written["frames_tracked"] == len(second_only)
