"""The Python API (slamkit/api.py, docs/api.md): the docs' example fed frame by frame gives `slamkit run`'s
trajectory and run directory bit for bit; the threaded runner tracks handed-in frames and joins its threads on
close; a frame that does not fit is refused with a clear error and the run goes on; a pipeline failure ends the run
and writes the run directory."""

from __future__ import annotations

import gc
import json
import re
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml

import slamkit
from slamkit.api import FrameInputError, System, SystemClosedError, open_system
from slamkit.eval.metrics import compute_ate
from slamkit.io.trajectory_io import read_trajectory, write_trajectory
from slamkit.pipeline.outcomes import TrackingState
from slamkit.sensors import Trajectory

DOC = Path(__file__).resolve().parents[2] / "docs" / "api.md"


def doc_example() -> str:
    """The first ```python block of docs/api.md."""
    match = re.search(r"```python\n(.*?)```", DOC.read_text(), re.S)
    assert match is not None, "docs/api.md has no python example"
    return match.group(1)


def slamkit_run(out: Path, *overrides: str) -> dict[str, Any]:
    """`slamkit run OVERRIDES` in a subprocess, into ``out``; its metrics."""
    result = subprocess.run(
        [sys.executable, "-m", "slamkit", "run", "runner.progress=false", *overrides, f"hydra.run.dir={out}"],
        cwd=out.parent,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert result.returncode == 0, result.stderr
    metrics: dict[str, Any] = json.loads((out / "metrics.json").read_text())
    return metrics


def assert_same_trajectory(api: Trajectory, tum_file: Path, tmp_path: Path) -> None:
    """The API's trajectory is the run's: same timestamps and camera centres bit for bit, and written as TUM the
    same file byte for byte (the rotation goes through a quaternion there, so the file is the exact comparison)."""
    run = read_trajectory(tum_file, "tum")
    assert len(api) == len(run) > 0
    assert np.array_equal(api.t_s, run.t_s)
    assert np.array_equal(api.positions_m, run.positions_m)
    written = tmp_path / "api_trajectory.tum"
    write_trajectory(written, api, "tum")
    assert written.read_bytes() == tum_file.read_bytes()


def test_docs_example_gives_slamkit_run_trajectory_and_run_directory_bit_for_bit(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)  # the example writes its run directory into the working directory
    namespace: dict[str, Any] = {}
    exec(compile(doc_example(), str(DOC), "exec"), namespace)
    overrides = namespace["overrides"]
    assert "runner=sequential" in overrides
    metrics = slamkit_run(tmp_path / "run", *overrides)
    assert metrics["status"] == "ok" and metrics["frames_tracked"] > 30
    assert_same_trajectory(namespace["trajectory"], tmp_path / "run" / "trajectory.tum", tmp_path)
    # the System's run directory is the run's (all but the timings)
    api_dir = tmp_path / "api_run"
    for name in ("trajectory.tum", "keyframes.tum", "loops.json", "maps/0/trajectory.tum"):
        assert (api_dir / name).read_bytes() == (tmp_path / "run" / name).read_bytes(), name
    configs = [yaml.safe_load((d / "config.yaml").read_text()) for d in (api_dir, tmp_path / "run")]
    for config in configs:
        config["runner"].pop("progress")  # the test's `slamkit run` hides its progress bar
    assert configs[0] == configs[1]
    api_metrics = json.loads((api_dir / "metrics.json").read_text())
    for key in ("status", "frames", "frames_tracked", "keyframes", "map_points", "ate_rmse_m", "kf_ate_rmse_m"):
        assert api_metrics[key] == metrics[key], key
    # the maps the example read are the run's map
    maps = namespace["maps"]
    assert len(maps) == 1 and maps[0].active
    assert maps[0].n_keyframes == metrics["keyframes"] and maps[0].n_points == metrics["map_points"]
    keyframes = read_trajectory(tmp_path / "run" / "keyframes.tum", "tum")
    assert np.array_equal(np.sort(maps[0].keyframe_timestamps_s), keyframes.t_s)
    assert np.allclose(np.linalg.inv(maps[0].T_c_w), maps[0].T_w_c, atol=1e-12)
    assert "keyframe(s)" in capsys.readouterr().out


@pytest.mark.slow
def test_whole_room_frame_by_frame_is_slamkit_run_bit_for_bit(tmp_path: Path) -> None:
    """The full room, its loop closed: the frames fed one by one give the run's trajectory bit for bit."""
    overrides = ["runner=sequential", "runner.progress=false"]
    metrics = slamkit_run(tmp_path / "run", *overrides)
    assert metrics["loops_closed"] >= 1
    with open_system(overrides) as system:
        for frame in system.dataset:
            system.track(frame.image, frame.timestamp_s, depth=frame.depth_m, imu=frame.imu)
        loops = sum(1 for lp in system.log.loops if lp.loop_kf_id is not None)
    assert loops == metrics["loops_closed"]
    assert_same_trajectory(system.trajectory(), tmp_path / "run" / "trajectory.tum", tmp_path)


def test_threaded_system_tracks_handed_frames_and_joins_its_threads_on_close(tmp_path: Path) -> None:
    system = open_system(["runner=threaded", "runner.progress=false", "dataset.max_frames=45"], output_dir=tmp_path)
    states = []
    for frame in system.dataset:
        result = system.track(frame.image, frame.timestamp_s, depth=frame.depth_m, imu=frame.imu)
        states.append(result.state)
        if result.tracked:
            assert result.T_w_c is not None and np.allclose(result.T_w_c @ result.T_c_w, np.eye(4), atol=1e-9)
    assert {t.name for t in threading.enumerate()} >= {"local-mapping", "loop-closing"}
    assert gc.get_freeze_count() > 0  # the warm-up froze the start-up heap for the run
    system.close()
    system.close()  # idempotent
    assert gc.get_freeze_count() == 0  # and the end gave it back: the embedding process collects it again
    assert not {t.name for t in threading.enumerate()} & {"local-mapping", "loop-closing", "lifecycle-events"}
    assert states[-1] == TrackingState.OK and states.count(TrackingState.OK) >= 30
    gt = system.dataset.ground_truth
    assert gt is not None
    ate = compute_ate(gt, system.trajectory(), align="sim3")
    assert ate.rmse_m < 0.02  # a 1.5 s stretch of the room: a few mm when tracking works
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["status"] == "ok" and metrics["runner"] == "threaded" and metrics["frames"] == len(states)
    assert metrics["keyframes"] == system.maps()[0].n_keyframes
    with pytest.raises(SystemClosedError, match="run has ended"):
        system.track(frame.image, frame.timestamp_s + 1.0)


@pytest.fixture(scope="module")
def small_system() -> System:
    return open_system(["runner=sequential", "runner.progress=false", "dataset.max_frames=12"])


def test_a_frame_that_does_not_fit_is_refused_and_the_run_goes_on(small_system: System) -> None:
    system = small_system
    frame = system.dataset[0]
    with pytest.raises(FrameInputError, match=r"shape \(240, 320\); expected \(480, 640\) uint8 grey"):
        system.track(frame.image[::2, ::2], frame.timestamp_s)
    with pytest.raises(FrameInputError, match="pixel type float32"):
        system.track(frame.image.astype(np.float32), frame.timestamp_s)
    with pytest.raises(FrameInputError, match="expected a numpy array"):
        system.track(frame.image.tolist(), frame.timestamp_s)  # type: ignore[arg-type]
    with pytest.raises(FrameInputError, match="depth of shape"):
        system.track(frame.image, frame.timestamp_s, depth=np.zeros((2, 2), np.float32))
    with pytest.raises(FrameInputError, match="float32 array of metres"):
        system.track(frame.image, frame.timestamp_s, depth=np.zeros((480, 640), np.uint16))
    assert not system.log.tracking  # nothing was tracked
    # a BGR frame is tracked as its grey conversion
    bgr = cv2.cvtColor(frame.image, cv2.COLOR_GRAY2BGR)
    first = system.track(bgr, frame.timestamp_s)
    assert first.frame_index == 0 and first.state == TrackingState.NOT_INITIALIZED
    assert system.log.tracking[-1].n_features > 100
    with pytest.raises(FrameInputError, match="does not increase"):
        system.track(frame.image, frame.timestamp_s)
    with pytest.raises(FrameInputError, match="frame_index = 0"):
        system.track(frame.image, frame.timestamp_s + 1.0, frame_index=0)
    second = system.track(system.dataset[1].image, system.dataset[1].timestamp_s)
    assert second.frame_index == 1 and len(system.log.tracking) == 2
    with pytest.raises(SystemClosedError, match="frames were tracked already"):
        system.run_dataset()
    system.close()
    assert system.closed
    with pytest.raises(SystemClosedError, match="run has ended"):
        system.track(frame.image, frame.timestamp_s + 2.0)


def test_rgbd_front_end_needs_depth_and_stereo_needs_the_right_image() -> None:
    rgbd = open_system(["frontend=rgbd", "runner=sequential", "dataset.max_frames=2"])
    frame = rgbd.dataset[0]
    with pytest.raises(FrameInputError, match=r"frontend=rgbd.*needs a depth map"):
        rgbd.track(frame.image, frame.timestamp_s)
    result = rgbd.track(frame.image, frame.timestamp_s, depth=frame.depth_m)
    assert result.state == TrackingState.OK and result.keyframe_made  # RGB-D initialises from one frame
    rgbd.close()
    stereo = open_system(["frontend=stereo", "dataset.stereo=true", "runner=sequential", "dataset.max_frames=2"])
    frame = stereo.dataset[0]
    with pytest.raises(FrameInputError, match=r"frontend=stereo.*needs the right image"):
        stereo.track(frame.image, frame.timestamp_s)
    assert stereo.track(frame.image, frame.timestamp_s, right=frame.image_right).keyframe_made
    stereo.close()


def test_a_pipeline_failure_ends_the_run_and_writes_the_run_directory(tmp_path: Path) -> None:
    system = open_system(["runner=sequential", "runner.progress=false", "dataset.max_frames=20"], output_dir=tmp_path)
    tracker = system.runner.tracker
    real_step = tracker.step

    def failing_step(data: Any, *args: Any) -> Any:
        if data.index == 14:
            raise RuntimeError("boom at frame 14")
        return real_step(data, *args)

    tracker.step = failing_step  # type: ignore[method-assign]
    with pytest.raises(RuntimeError, match="boom"):
        for frame in system.dataset:
            system.track(frame.image, frame.timestamp_s)
    assert system.closed
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["status"] == "failed" and "boom at frame 14" in metrics["error"]
    # what was tracked before the failure is kept: the map initialised at frame 10 (with its reference frame), then
    # frames 11..13
    assert metrics["frames_tracked"] == 5 == len(read_trajectory(tmp_path / "trajectory.tum", "tum"))
    with pytest.raises(SystemClosedError, match="boom at frame 14"):
        system.track(frame.image, frame.timestamp_s + 1.0)
    system.close()  # nothing left to do


def test_a_failing_with_block_ends_the_run_as_failed(tmp_path: Path) -> None:
    with pytest.raises(KeyError), open_system(["runner=sequential", "dataset.max_frames=3"], output_dir=tmp_path):
        raise KeyError("the caller's own bug")
    assert json.loads((tmp_path / "metrics.json").read_text())["status"] == "failed"


def test_config_dir_adds_config_groups_of_ones_own(tmp_path: Path) -> None:
    (tmp_path / "dataset").mkdir()
    (tmp_path / "dataset" / "small_room.yaml").write_text(
        "defaults:\n  - synthetic\n  - _self_\nwidth: 320\nheight: 240\nfx: 235.0\nfy: 235.0\nmax_frames: 2\n"
    )
    system = open_system(["dataset=small_room", "runner=sequential"], config_dir=tmp_path)
    assert (system.camera.width, system.camera.height) == (320, 240)
    with pytest.raises(FrameInputError, match=r"expected \(240, 320\)"):
        system.track(np.zeros((480, 640), np.uint8), 0.0)
    system.close()
    with pytest.raises(FileNotFoundError, match="config_dir"):
        open_system([], config_dir=tmp_path / "missing")


def test_the_api_is_reexported_from_slamkit_and_imported_on_first_use() -> None:
    assert slamkit.open_system is open_system and slamkit.System is System
    code = "import sys, slamkit; assert 'slamkit.api' not in sys.modules; slamkit.open_system; print('ok')"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.stdout.strip() == "ok", result.stderr


def test_a_system_saves_its_map_and_a_new_system_relocalizes_in_it(tmp_path: Path) -> None:
    """System.save_map writes slamkit's map file; a system opened with map.load relocalizes in it at once."""
    from slamkit.map.mapfile import read_atlas

    path = tmp_path / "room.slamkit"
    with open_system(["runner=sequential", "dataset.max_frames=60"]) as system:
        system.run_dataset()
        info = system.save_map(path)
        kept = {map_id: store.keyframe_ids() for map_id, store in system.atlas.items()}
    assert info.n_keyframes == sum(len(k) for k in kept.values()) > 5
    assert {map_id: store.keyframe_ids() for map_id, store in read_atlas(path).items()} == kept
    with open_system(
        ["runner=sequential", "dataset.max_frames=20", "dataset.skip=[0,49]", f"map.load={path}"]
    ) as again:
        frame = again.dataset[0]  # frame 50 of the room: ground the saved map covers
        first = again.track(frame.image, frame.timestamp_s)
        assert first.method == "relocalization" and first.state.value == "ok", first.message
