"""The rerun viewer plugin (plugins/slamkit_rerun): a run recorded to an .rrd file with ``+viewer=rerun
viewer.save=FILE`` holds what the run made — every keyframe at its final pose, the final map points, the frames'
features, the loop — read back with rerun's own reader; a failing viewer never stops the run."""

from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from omegaconf import OmegaConf

from slamkit.app import build_runner
from slamkit.config import compose_config
from slamkit.errors import ConfigError

rerun_chunk = pytest.importorskip("rerun.chunk", reason="rerun-sdk is not installed (pip install 'slamkit[viewer]')")

from slamkit_rerun.settings import ViewerSettings  # noqa: E402
from slamkit_rerun.viewer import PointCloud, RerunViewer, age_colours  # noqa: E402


def read_rrd(path: Path) -> dict[str, list[dict[str, Any]]]:
    """Every logged row of an .rrd file, per entity path, in log order: {entity: [{column: value}, ...]}."""
    rows: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for chunk in rerun_chunk.RrdReader(path).stream():
        table = chunk.to_record_batch().to_pylist()
        rows[chunk.entity_path].extend(table)
    return rows


def last_positions(rows: list[dict[str, Any]], column: str = "Points3D:positions") -> np.ndarray:
    """The positions of the entity's last row with that column, (N, 3) or (N, 2)."""
    value = next(r[column] for r in reversed(rows) if r.get(column) is not None)
    return np.asarray(value, dtype=np.float64)


def run_with_viewer(tmp_path: Path, *overrides: str) -> tuple[Any, Any]:
    cfg = compose_config(["runner=sequential", "runner.progress=false", "+viewer=rerun", *overrides])
    runner, dataset = build_runner(cfg)
    config = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(config, dict)
    runner.run(dataset, dataset.camera, config={str(k): v for k, v in config.items()})
    return runner, dataset


def check_final_map(rrd: Path, runner: Any) -> dict[str, list[dict[str, Any]]]:
    rows = read_rrd(rrd)
    store = runner.atlas.get(0)
    # every keyframe of the final map at its final pose (centres), labelled by id
    kf_ids = store.keyframe_ids()
    last_kfs = next(r for r in reversed(rows["/world/map_0/keyframes"]) if r.get("Points3D:positions") is not None)
    assert [int(x) for x in last_kfs["Points3D:labels"]] == kf_ids
    centres = np.stack([store.get_keyframe(k).T_w_c[:3, 3] for k in kf_ids])
    np.testing.assert_allclose(np.asarray(last_kfs["Points3D:positions"]), centres, atol=1e-5)  # float32 in rerun
    # every final map point at its final position
    point_ids = np.array(sorted(store.point_ids()), dtype=np.int64)
    xyz = last_positions(rows["/world/map_0/points"])
    assert xyz.shape == (len(point_ids), 3)
    np.testing.assert_allclose(xyz, store.point_rows(point_ids, "xyz_w"), atol=1e-4)
    return rows


def test_a_recorded_run_holds_every_keyframe_the_final_points_and_each_frames_features(tmp_path: Path) -> None:
    rrd = tmp_path / "room.rrd"
    runner, _ = run_with_viewer(
        tmp_path,
        "dataset.max_frames=70",
        f"viewer.save={rrd}",
        "viewer.image_every=10",
        "viewer.skip_stale_frames=false",
    )
    rows = check_final_map(rrd, runner)
    frames = len(runner.log.tracking)
    assert len(rows["/world/camera/image/features"]) == frames
    assert len(rows["/plots/track_ms"]) == len(rows["/plots/inliers"]) == frames  # sent in columns, every frame
    assert len(rows["/world/camera/image"]) >= frames // 10  # JPEG every 10th frame (+ the static pinhole)
    tracked = sum(1 for o in runner.log.tracking if o.T_c_w is not None)
    assert len([r for r in rows["/world/camera"] if r.get("Transform3D:translation") is not None]) == tracked
    texts = [t for r in rows["/events"] for t in (r.get("TextLog:text") or [])]
    assert any("map 0 initialised" in t for t in texts) and any(t.startswith("run ok") for t in texts)


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_the_whole_room_recording_holds_the_loop_event(tmp_path: Path) -> None:
    rrd = tmp_path / "room.rrd"
    runner, _ = run_with_viewer(tmp_path, f"viewer.save={rrd}", "viewer.image_every=30")
    rows = check_final_map(rrd, runner)
    loops = [lp for lp in runner.log.loops if lp.loop_kf_id is not None]
    assert len(loops) == 1
    texts = [t for r in rows["/events"] for t in (r.get("TextLog:text") or [])]
    expected = f"loop closed: keyframe {loops[0].kf_id} <-> {loops[0].loop_kf_id}"
    assert sum(t.startswith(expected) for t in texts) == 1
    assert "/world/loops/0" in rows


def plain_run(frames: int) -> Any:
    cfg = compose_config(["runner=sequential", "runner.progress=false", f"dataset.max_frames={frames}"])
    plain, dataset = build_runner(cfg)
    plain.run(dataset, dataset.camera)
    return plain


def test_a_failing_viewer_is_logged_once_and_the_run_goes_on_unchanged(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    plain = plain_run(40)
    calls = []

    def broken(self: RerunViewer, event: Any, stale: bool = False) -> None:
        calls.append(event.frame_index)
        if event.frame_index == 20:
            raise RuntimeError("display went away")

    monkeypatch.setattr(RerunViewer, "frame_tracked", broken)  # reaches a viewer in this process only
    with caplog.at_level(logging.WARNING, logger="slamkit_rerun.plugin"):
        viewed, _ = run_with_viewer(
            tmp_path, "dataset.max_frames=40", f"viewer.save={tmp_path / 'v.rrd'}", "viewer.process=false"
        )
    assert calls == list(range(21)), "the viewer stops at its failure"
    warnings = [r.getMessage() for r in caplog.records if "display went away" in r.getMessage()]
    assert len(warnings) == 1 and "the run goes on" in warnings[0]
    np.testing.assert_array_equal(viewed.recorder.frames(viewed.store).T_w_c, plain.recorder.frames(plain.store).T_w_c)


def test_a_viewer_process_that_dies_is_logged_once_and_the_run_goes_on_unchanged(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    plain = plain_run(40)
    killed: list[int] = []

    def kill_the_viewer() -> None:  # as soon as the run has started its viewer process
        deadline = time.monotonic() + 60.0
        while not killed and time.monotonic() < deadline:
            for child in multiprocessing.active_children():
                if child.name.startswith("slamkit-viewer-") and child.pid is not None:
                    os.kill(child.pid, signal.SIGKILL)
                    killed.append(child.pid)
            time.sleep(0.01)

    killer = threading.Thread(target=kill_the_viewer, daemon=True)
    killer.start()
    with caplog.at_level(logging.WARNING, logger="slamkit_rerun.plugin"):
        viewed, _ = run_with_viewer(tmp_path, "dataset.max_frames=40", f"viewer.save={tmp_path / 'v.rrd'}")
    killer.join()
    assert killed, "the viewer process was never seen"
    warnings = [r.getMessage() for r in caplog.records if "the run goes on" in r.getMessage()]
    assert len(warnings) == 1 and "exit code -9" in warnings[0]
    np.testing.assert_array_equal(viewed.recorder.frames(viewed.store).T_w_c, plain.recorder.frames(plain.store).T_w_c)


def test_an_unwritable_recording_file_leaves_the_run_alone(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    with caplog.at_level(logging.WARNING, logger="slamkit_rerun.plugin"):
        runner, _ = run_with_viewer(tmp_path, "dataset.max_frames=15", f"viewer.save={blocker / 'x.rrd'}")
    assert len(runner.log.tracking) == 15
    assert any("could not open rerun" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize(
    ("node", "message"),
    [
        ({"kind": "rerun", "image_every": 0}, "viewer.image_every = 0"),
        ({"kind": "rerun", "jpeg_quality": 101}, "viewer.jpeg_quality = 101"),
        ({"kind": "rerun", "save": "a.rrd", "connect": "rerun+http://h:9876/proxy"}, "both set"),
    ],
)
def test_bad_viewer_settings_name_the_key(node: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        ViewerSettings.from_config({"viewer": node})


def test_no_viewer_group_means_no_viewer_and_points_are_coloured_old_to_new() -> None:
    assert ViewerSettings.from_config({}) is None and ViewerSettings.from_config({"viewer": {"kind": "x"}}) is None
    colours = age_colours(np.array([7, 3, 11], dtype=np.int64))
    assert tuple(colours[1]) == (40, 90, 255) and tuple(colours[2]) == (255, 220, 40)  # oldest blue, youngest yellow


def test_the_point_cloud_keeps_each_points_latest_position_in_id_order() -> None:
    cloud = PointCloud()
    cloud.update(np.array([5, 2], np.int64), np.array([[5.0, 0, 0], [2.0, 0, 0]]))
    cloud.update(np.array([5, 3000], np.int64), np.array([[5.5, 0, 0], [30.0, 0, 0]]))  # moved, and a new one
    ids, xyz = cloud.points()
    assert ids.tolist() == [2, 5, 3000] and xyz[:, 0].tolist() == [2.0, 5.5, 30.0] and len(cloud) == 3
