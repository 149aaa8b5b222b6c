"""A MapStore written by a third party against the protocol only (tests/plugins/slamkit_dictmap, ``map=dict``) runs
the synthetic room end to end, and the pipeline on it computes exactly what it computes on the in-memory store: the
pipeline depends on the MapStore protocol, not on slamkit's own store."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slamkit.app import build_runner
from slamkit.config import compose_config
from slamkit.plugins import ComponentRegistry
from slamkit.sensors import Trajectory


def run_room(store: str, registry: ComponentRegistry, extra: list[str]) -> tuple[Trajectory, Trajectory, int]:
    """(frame trajectory, keyframe trajectory, map points) of a sequential run of the room with ``map=<store>``."""
    overrides = ["runner=sequential", "runner.progress=false", "seed=0", f"map={store}", *extra]
    runner, dataset = build_runner(compose_config(overrides, registry=registry), registry)
    assert type(runner.store).__module__.startswith("slamkit_dictmap" if store == "dict" else "slamkit.map")
    runner.run(dataset, dataset.camera)
    return runner.recorder.frames(runner.store), runner.recorder.keyframes(runner.store), runner.store.n_points()


def assert_same_run(extra: list[str], min_frames: int) -> None:
    registry = ComponentRegistry.discover()
    frames, keyframes, n_points = run_room("memory", registry, extra)
    frames_d, keyframes_d, n_points_d = run_room("dict", registry, extra)
    assert len(frames) >= min_frames and len(keyframes) >= 10
    np.testing.assert_array_equal(frames_d.t_s, frames.t_s)
    np.testing.assert_array_equal(frames_d.T_w_c, frames.T_w_c)  # bit for bit
    np.testing.assert_array_equal(keyframes_d.T_w_c, keyframes.T_w_c)
    assert n_points_d == n_points


@pytest.mark.timeout(600)
def test_the_minimal_store_tracks_the_room_exactly_as_the_in_memory_store(dictmap_plugin: Path) -> None:
    assert_same_run(["dataset.max_frames=90"], min_frames=80)  # the whole room: the slow test below


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_the_minimal_store_runs_the_whole_room_with_its_loop_exactly_as_the_in_memory_store(
    dictmap_plugin: Path,
) -> None:
    assert_same_run([], min_frames=800)
