"""The lifecycle hooks on real runs: a third-party plugin distribution (tests/plugins/slamkit_hookcount),
pip-installed by the test, counts frames, keyframes and loops through them and agrees with metrics.json in both
runners; the outputs plugin's files agree with the runner's own account; a failing listener does not stop the
run, a failing outputs plugin fails it."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

import slamkit.eval.outputs
from slamkit.app import build_runner
from slamkit.config import compose_config
from slamkit.errors import PluginError
from slamkit.eval.run_metrics import runner_metrics
from slamkit.events import FrameTracked
from slamkit.hookspecs import hookimpl
from slamkit.io.trajectory_io import write_trajectory
from slamkit.plugins import ComponentRegistry

pytestmark = pytest.mark.timeout(1200)

PLUGINS_DIR = Path(__file__).resolve().parents[1] / "plugins"


@pytest.fixture(scope="module")
def hookcount_site(tmp_path_factory: pytest.TempPathFactory, pip_install: Callable[..., Path]) -> Iterator[Path]:
    """pip-installs the example distribution into a private folder (not on this process's sys.path)."""
    yield pip_install(tmp_path_factory.mktemp("site"), PLUGINS_DIR / "slamkit_hookcount")


def run_with_hookcount(site: Path, out: Path, *overrides: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """`slamkit run` with the counting plugin installed: (metrics.json, hook_counts.json)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")])}
    result = subprocess.run(
        [sys.executable, "-m", "slamkit", "run", "runner.progress=false", f"hydra.run.dir={out}", *overrides],
        env=env,
        capture_output=True,
        text=True,
        timeout=3600,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    return json.loads((out / "metrics.json").read_text()), json.loads((out / "hook_counts.json").read_text())


def assert_counts_match(metrics: dict[str, Any], counts: dict[str, Any], runner: str) -> None:
    assert counts["status"] == metrics["status"] == "ok"
    assert counts["frames_tracked"] == metrics["frames"]
    # one map, never reset: every keyframe local mapping inserted is in the map at the end unless culled
    assert metrics["resets"] == counts["resets"] == 0
    assert counts["maps_created"] == 1
    assert counts["keyframes_inserted"] - counts.get("keyframes_culled", 0) == metrics["keyframes"]
    assert counts["keyframes_at_end"] == metrics["keyframes"]
    assert counts.get("loops_closed", 0) == metrics["loops_closed"]
    # sequential: listeners run in the one pipeline thread; threaded: all on the dispatcher's own thread
    assert counts["threads"] == (["MainThread"] if runner == "sequential" else ["lifecycle-events"])


# the sequential runner's events are also checked against its own record by the outputs test above: slow here
@pytest.mark.parametrize("runner", [pytest.param("sequential", marks=pytest.mark.slow), "threaded"])
def test_third_party_plugin_counts_frames_and_keyframes_like_metrics_json(
    hookcount_site: Path, tmp_path: Path, runner: str
) -> None:
    metrics, counts = run_with_hookcount(hookcount_site, tmp_path / "run", f"runner={runner}", "dataset.max_frames=70")
    assert metrics["frames"] == 70 and metrics["keyframes"] >= 4
    if runner == "sequential":  # deterministic: 24 keyframes inserted, 13 culled (so the subtraction is tested)
        assert counts["keyframes_culled"] > 0
    assert_counts_match(metrics, counts, runner)


@pytest.mark.slow
@pytest.mark.timeout(4 * 3600)
@pytest.mark.parametrize("runner", ["sequential", "threaded"])
def test_third_party_plugin_counts_the_rooms_loop_like_metrics_json(
    hookcount_site: Path, tmp_path: Path, runner: str
) -> None:
    """The whole room (840 frames) closes its one loop (~frame 800): the plugin sees it in both runners."""
    metrics, counts = run_with_hookcount(hookcount_site, tmp_path / "run", f"runner={runner}")
    assert metrics["loops_closed"] == 1 and counts["loops_closed"] == 1
    assert counts.get("keyframes_culled", 0) > 0  # culling happened, so the subtraction is tested too
    assert_counts_match(metrics, counts, runner)


@pytest.mark.parametrize("runner", ["sequential", "threaded"])
def test_outputs_plugin_writes_what_the_runner_itself_recorded(tmp_path: Path, runner: str) -> None:
    """metrics.json and trajectory.tum, rebuilt by the outputs plugin from the events alone, equal what the
    runner's own RunLog, trajectory recorder and store give (same run: same numbers, bit for bit)."""
    cfg = compose_config([f"runner={runner}", "runner.progress=false", "dataset.max_frames=45"])
    runner_obj, dataset = build_runner(cfg)
    runner_obj.run(dataset, dataset.camera, run_dir=tmp_path, config={"seed": 0})
    written = json.loads((tmp_path / "metrics.json").read_text())
    expected = json.loads(json.dumps(runner_metrics(runner_obj, dataset), default=float))
    assert written.pop("status") == "ok" and written.pop("seed") == 0
    assert written == expected
    for name, traj in (
        ("trajectory.tum", runner_obj.recorder.frames(runner_obj.store)),
        ("keyframes.tum", runner_obj.recorder.keyframes(runner_obj.store)),
    ):
        write_trajectory(tmp_path / "expected.tum", traj, "tum")
        assert len(traj) >= 5
        assert (tmp_path / name).read_text() == (tmp_path / "expected.tum").read_text(), name


class _BrokenViewer:
    """A listener that fails on the fifth frame."""

    def __init__(self) -> None:
        self.frames = 0

    @hookimpl
    def slamkit_frame_tracked(self, event: FrameTracked) -> None:
        self.frames += 1
        if self.frames == 5:
            raise RuntimeError("viewer window closed")


def test_a_failing_listener_is_logged_by_name_and_the_run_goes_on(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    registry = ComponentRegistry.discover()
    viewer = _BrokenViewer()
    registry.add_plugin("broken_viewer", viewer, "test")
    cfg = compose_config(["runner=sequential", "runner.progress=false", "dataset.max_frames=20"])
    runner, dataset = build_runner(cfg, registry)
    with caplog.at_level(logging.ERROR, logger="slamkit.events"):
        runner.run(dataset, dataset.camera, run_dir=tmp_path, config={"seed": 0})
    assert viewer.frames == 5  # not called again after its failure
    assert "plugin 'broken_viewer' failed in slamkit_frame_tracked" in caplog.text
    assert "viewer window closed" in caplog.text
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["status"] == "ok" and metrics["frames"] == 20


def test_a_failing_outputs_plugin_fails_the_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def broken_write(out_dir: Path, record: object) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(slamkit.eval.outputs, "write_outputs", broken_write)
    cfg = compose_config(["runner=sequential", "runner.progress=false", "dataset.max_frames=12"])
    runner, dataset = build_runner(cfg)
    with pytest.raises(PluginError, match=r"plugin 'outputs' \(the run's outputs\) failed in slamkit_run_finished"):
        runner.run(dataset, dataset.camera, run_dir=tmp_path, config={"seed": 0})
