"""The threaded runner on the synthetic room: it tracks like the sequential runner, and a failure in any of its
threads stops the run with that thread's name, keeps what was computed, and never hangs."""

from __future__ import annotations

import json
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from ctrl_c import interrupt_after

from slamkit.app import build_runner
from slamkit.config import compose_config
from slamkit.eval.run_metrics import runner_metrics
from slamkit.pipeline.local_mapping import LocalMapper
from slamkit.runtime.threaded import ThreadedRunner
from slamkit.runtime.workers import PipelineThreadError, PipelineWorker

pytestmark = pytest.mark.timeout(600)

BASE = ["runner=threaded", "runner.progress=false", "dataset.max_frames=150"]


def _runner(*overrides: str) -> tuple[ThreadedRunner, Any]:
    runner, dataset = build_runner(compose_config([*BASE, *overrides]))
    assert isinstance(runner, ThreadedRunner)
    return runner, dataset


def _served_frames(runner: ThreadedRunner) -> list[int]:
    """The frames tracking will take from the frame source's extractions ahead, listed as the run goes (a spy on
    ``_count_extraction_ahead``)."""
    served: list[int] = []
    count = runner._count_extraction_ahead

    def noted(out: Any, data: Any) -> None:
        if runner._ahead is not None and data.index in runner._ahead._served_ms:
            served.append(data.index)
        count(out, data)

    runner._count_extraction_ahead = noted  # type: ignore[method-assign]
    return served


def _fail_on_call(n: int, message: str):  # type: ignore[no-untyped-def]
    """A replacement for a step function that works normally n-1 times and raises on the n-th call."""
    calls = {"n": 0}

    def wrap(real):  # type: ignore[no-untyped-def]
        def step(*args: Any, **kwargs: Any) -> Any:
            calls["n"] += 1
            if calls["n"] == n:
                raise RuntimeError(message)
            return real(*args, **kwargs)

        return step

    return wrap


def test_threaded_run_tracks_the_room_as_accurately_as_the_sequential_one(
    assert_no_culled_keyframe_alive: Callable[[Any], None],
) -> None:
    runner, dataset = _runner()
    log = runner.run(dataset, dataset.camera)
    assert_no_culled_keyframe_alive(runner)
    metrics = runner_metrics(runner, dataset)
    assert metrics["runner"] == "threaded" and metrics["frames_dropped"] == 0
    assert metrics["frames"] == 150
    assert metrics["frames_tracked"] >= 150 - 12  # initialises at frame ~10, then tracks every frame
    assert metrics["keyframes"] >= 5 and len(log.mapping) >= metrics["keyframes"]
    # room's path over 5 s is ~2.4 m: 1% of it; the sequential runner reaches ~0.1-0.2%
    assert metrics["ate_rmse_pct_of_path"] < 1.0
    assert metrics["realtime_factor"] is not None and metrics["realtime_factor"] > 0


# frame_waits_for=none is not the default policy: its variant is slow (the default one runs in the default suite)
@pytest.mark.parametrize("waits_for", ["local_mapping", pytest.param("none", marks=pytest.mark.slow)])
def test_as_fast_as_possible_the_modelled_mapping_time_keeps_keyframes_apart_in_sequence_time(waits_for: str) -> None:
    """``runner.modelled_mapping_ms`` as fast as possible: a monocular frame within the modelled time of the last
    keyframe makes none (ORB-SLAM's monocular NeedNewKeyFrame while local mapping is busy), whatever the local
    mapping thread is doing. With ``frame_waits_for=local_mapping`` (the default) every frame, inside the modelled time
    or past it, is tracked once local mapping is done with the keyframes before it (the sequential runner's map and
    model); with ``none`` a frame inside it is tracked at once, and only a frame past it waits for the thread to
    finish the keyframes before it (a camera's frame would find them mapped). Keyframes are made and the room is
    tracked either way."""
    busy_s = 0.25
    runner, dataset = _runner(
        f"runner.modelled_mapping_ms={busy_s * 1e3:g}",
        "runner.modelled_mapping_new_map_ms=0",
        f"runner.frame_waits_for={waits_for}",
    )
    # wall clock when tracking got local mapping's state for each frame and when local mapping was done with each
    # keyframe
    state_at: dict[float, float] = {}
    mapped_at: dict[int, float] = {}
    assert runner.mapper is not None
    mapping_state, mapper_step = runner._mapping_state, runner.mapper.step

    def timed_state(timestamp_s: float) -> Any:
        state = mapping_state(timestamp_s)
        state_at[timestamp_s] = time.perf_counter()
        return state

    def timed_map(kf: Any, *args: Any, **kwargs: Any) -> Any:
        out = mapper_step(kf, *args, **kwargs)
        mapped_at[kf.id] = time.perf_counter()
        return out

    runner._mapping_state, runner.mapper.step = timed_state, timed_map  # type: ignore[method-assign]
    log = runner.run(dataset, dataset.camera)
    made = [out.timestamp_s for out in log.tracking if out.keyframe_ids and not out.initialized_map]
    assert len(made) >= 5
    gaps = np.diff(made)
    assert gaps.min() >= busy_s - 1e-9, gaps
    inside = [out for out in log.tracking if any(0 < out.timestamp_s - t < busy_s for t in made)]
    assert inside
    if waits_for == "none":
        # frames inside a keyframe's modelled time never wait for the local mapping thread
        assert all("mapping_wait_ms" not in out.timings_ms for out in inside)
    for out in log.tracking:
        if out.keyframe_ids and not out.initialized_map:
            # local_mapping: every later frame; none: the frames past the keyframe's modelled time
            first = out.timestamp_s if waits_for == "local_mapping" else out.timestamp_s + busy_s - 1e-9
            later = [t for t in state_at if t > first]
            assert all(state_at[t] >= mapped_at[k] for t in later for k in out.keyframe_ids)
    if waits_for == "local_mapping":
        # some frame inside a modelled time waited for the thread: the sequential runner's map, not the thread's
        assert any("mapping_wait_ms" in out.timings_ms for out in inside)
    metrics = runner_metrics(runner, dataset)
    assert metrics["frames_tracked"] >= 150 - 12 and metrics["ate_rmse_pct_of_path"] < 1.0


@pytest.mark.slow  # runner.wait_for_local_mapping=false is not the default policy
def test_as_fast_as_possible_without_waiting_a_busy_local_mapping_gets_no_keyframe_and_tracking_never_waits() -> None:
    """``runner.wait_for_local_mapping=false``: ORB-SLAM2/3 fed as fast as they track. Tracking never waits for local
    mapping; a monocular frame that wants a keyframe while it is busy interrupts its local BA and makes none, so each
    keyframe is handed to an idle local mapping (the thread slowed here to 0.3 s a keyframe, ten frame periods)."""
    runner, dataset = _runner("runner.wait_for_local_mapping=false")
    busy: list[tuple[float, float]] = []  # wall clock spans local mapping worked on a keyframe
    tracked: dict[int, tuple[float, float]] = {}  # wall clock span each keyframe's frame was tracked in
    mapper_step = runner.mapper.step
    track = runner._track

    def slow_map(kf: Any, *args: Any, **kwargs: Any) -> Any:
        t0 = time.perf_counter()
        time.sleep(0.2)
        out = mapper_step(kf, *args, **kwargs)
        busy.append((t0, time.perf_counter()))
        return out

    def timed_track(data: Any, camera: Any) -> Any:
        t0 = time.perf_counter()
        time.sleep(1 / 30)  # a camera's frame period
        out = track(data, camera)
        for kf_id in out.keyframe_ids:
            tracked[kf_id] = (t0, time.perf_counter())
        return out

    runner.mapper.step = slow_map  # type: ignore[method-assign]
    runner._track = timed_track  # type: ignore[method-assign]
    log = runner.run(dataset, dataset.camera)
    assert all("mapping_wait_ms" not in out.timings_ms for out in log.tracking)
    made = [out for out in log.tracking if out.keyframe_ids and not out.initialized_map]
    assert len(made) >= 2
    # a keyframe is made only when local mapping is idle: never by a frame tracked while the thread worked on an
    # earlier keyframe from the frame's start to its end
    for out in made:
        start, end = tracked[out.keyframe_ids[0]]
        assert not any(t0 < start and end < t1 for t0, t1 in busy), out.frame_index
    # at most one keyframe per 0.2 s of local mapping over the run's wall time, besides each map's first two
    wall_s = log.wall_s
    assert len(log.mapping) <= 2 * (1 + log.resets) + wall_s / 0.2 + 1


# frame_waits_for=none is not the default policy: its variant is slow (the default one runs in the default suite)
@pytest.mark.parametrize("waits_for", ["local_mapping", pytest.param("none", marks=pytest.mark.slow)])
def test_as_fast_as_possible_a_frame_is_tracked_once_local_mapping_is_done_with_the_keyframes_before_it(
    waits_for: str,
) -> None:
    """``runner.frame_waits_for``. local_mapping (the default): each monocular frame is tracked (after its
    extraction, which runs beside local mapping) only once local mapping is done with every keyframe made before it, so
    it is never tracked, nor decides on a keyframe, with local mapping busy; none: frames are tracked while local
    mapping works (the thread's triangulation slowed to 0.1 s here)."""
    runner, dataset = _runner(f"runner.frame_waits_for={waits_for}", "runner.modelled_mapping_ms=0")
    tracked_from: dict[float, float] = {}  # frame timestamp -> wall clock when tracking got local mapping's state
    extracted: dict[float, float] = {}  # frame timestamp -> wall clock when its feature extraction began
    mapped_at: dict[int, float] = {}  # keyframe id -> wall clock when local mapping was done with it
    assert runner.mapper is not None
    mapping_state, mapper_step, observe = runner._mapping_state, runner.mapper.step, runner.tracker.frontend.observe
    create_new_points = runner.mapper._create_new_points

    def slow_triangulation(*args: Any, **kwargs: Any) -> Any:
        time.sleep(0.1)
        return create_new_points(*args, **kwargs)

    def timed_observe(data: Any, *args: Any, **kwargs: Any) -> Any:
        extracted.setdefault(data.timestamp_s, time.perf_counter())
        return observe(data, *args, **kwargs)

    def timed_state(timestamp_s: float) -> Any:
        state = mapping_state(timestamp_s)
        tracked_from[timestamp_s] = time.perf_counter()
        return state

    def timed_map(kf: Any, *args: Any, **kwargs: Any) -> Any:
        out = mapper_step(kf, *args, **kwargs)
        mapped_at[kf.id] = time.perf_counter()
        return out

    busy_decisions: list[int] = []  # frames that wanted a keyframe while local mapping was busy
    wanted_while_busy = runner._keyframe_wanted_while_mapping_busy

    def noted_busy(out: Any) -> Any:
        busy_decisions.append(out.frame_index)
        return wanted_while_busy(out)

    runner._keyframe_wanted_while_mapping_busy = noted_busy  # type: ignore[method-assign]
    runner.mapper._create_new_points = slow_triangulation  # type: ignore[method-assign]
    runner.tracker.frontend.observe = timed_observe  # type: ignore[method-assign]
    runner._mapping_state, runner.mapper.step = timed_state, timed_map  # type: ignore[method-assign]
    log = runner.run(dataset, dataset.camera)
    made = [(out.timestamp_s, kf_id) for out in log.tracking for kf_id in out.keyframe_ids]
    assert len(made) >= 5
    later = [(extracted[t], tracked_from[t], mapped_at[k]) for t_kf, k in made for t in tracked_from if t > t_kf]
    if waits_for == "local_mapping":
        assert all(start >= done for _, start, done in later)
        assert busy_decisions == []  # every keyframe decision found local mapping idle, as the sequential runner's
        # the next frame's extraction ran beside local mapping's work on the keyframe before it
        assert any(extraction < done for extraction, _, done in later)
    else:
        assert any(start < done for _, start, done in later) and busy_decisions
    metrics = runner_metrics(runner, dataset)
    assert metrics["frames_tracked"] >= 150 - 12 and metrics["ate_rmse_pct_of_path"] < 1.0


def test_features_extracted_ahead_leave_the_sequential_runners_trajectory_bit_for_bit(tmp_path: Path) -> None:
    """``runner.extract_ahead`` (default 8): the frame source extracts the features of the frames it reads ahead, on
    the core local mapping leaves idle. Tracking takes those records for the frames after the map's initialisation
    (its frames get the initialisation extractor from tracking itself), and the run as fast as possible is still the
    sequential runner's, bit for bit (frame_waits_for=local_mapping with the modelled mapping time)."""
    frames = "dataset.max_frames=70"
    sequential, dataset = build_runner(compose_config(["runner=sequential", "runner.progress=false", frames]))
    sequential.run(dataset, dataset.camera, run_dir=tmp_path / "sequential", config={"seed": 0})
    runner, dataset = _runner(frames)
    assert runner.extract_ahead == 8
    served = _served_frames(runner)
    log = runner.run(dataset, dataset.camera, run_dir=tmp_path / "threaded", config={"seed": 0})
    first = next(out.frame_index for out in log.tracking if out.initialized_map)
    # every frame past the initialisation extractor's window (ORB-SLAM3: 30 frames after the map's first) is served
    window = runner.tracker.max_frames
    assert served and set(range(first + window + 1, 70)) <= set(served) and min(served) > first
    assert (tmp_path / "threaded" / "trajectory.tum").read_bytes() == (
        tmp_path / "sequential" / "trajectory.tum"
    ).read_bytes()
    assert all(out.timings_ms["extract_ms"] > 1.0 for out in log.tracking if out.frame_index in served)


def test_not_waiting_for_local_mapping_leaves_the_modelled_time_unused() -> None:
    """``runner.wait_for_local_mapping=false``: the local mapping thread's own state decides, as in real time; the
    modelled mapping time (default 100 ms) stands in for a camera's frame period only when frames wait."""
    runner, _ = _runner("runner.wait_for_local_mapping=false", "runner.modelled_mapping_ms=100")
    assert not runner.modelled_mapping.enabled
    runner, _ = _runner("runner.modelled_mapping_ms=100")
    assert runner.modelled_mapping.enabled


@pytest.mark.parametrize(
    ("thread", "target"),
    [("tracking", "tracker"), ("local-mapping", "mapper"), ("loop-closing", "loop_closer"), ("frame-source", None)],
)
def test_a_failure_in_any_thread_stops_the_run_with_its_name_and_keeps_the_trajectory(
    thread: str, target: str | None
) -> None:
    runner, dataset = _runner()
    message = f"injected failure in {thread}"
    if target is None:
        frames = iter(dataset)

        def failing_frames():  # type: ignore[no-untyped-def]
            for i, data in enumerate(frames):
                if i == 60:
                    raise OSError(message)
                yield data

        dataset_to_play: Any = failing_frames()
        dataset_to_play_len = len(dataset)
    else:
        component = getattr(runner, target)
        method = "detect" if target == "loop_closer" else "step"  # loop closing's thread starts with detection
        setattr(
            component, method, _fail_on_call(40 if thread == "tracking" else 8, message)(getattr(component, method))
        )
        dataset_to_play = dataset
        dataset_to_play_len = len(dataset)

    class Played:
        def __len__(self) -> int:
            return dataset_to_play_len

        def __iter__(self):  # type: ignore[no-untyped-def]
            return iter(dataset_to_play)

    t0 = time.perf_counter()
    with pytest.raises(PipelineThreadError) as info:
        runner.run(Played(), dataset.camera)  # type: ignore[arg-type]
    assert info.value.thread_name == thread
    assert message in str(info.value) and "Traceback" in info.value.formatted_traceback
    assert runner.log.failed_thread == thread
    # it stopped early (150 frames take far longer than the failure point) and kept what it had
    assert len(runner.log.tracking) < 150
    if thread == "frame-source":
        assert len(runner.log.tracking) == 60  # the frames read before the failure are all tracked
    assert len(runner.recorder.frames(runner.store)) >= 10
    assert time.perf_counter() - t0 < 300
    for name in ("local-mapping", "loop-closing", "frame-source"):
        for t in __import__("threading").enumerate():
            if t.name == name:
                t.join(timeout=30)
                assert not t.is_alive(), f"{name} still running after the failure"


def test_slamkit_run_writes_a_failed_run_and_exits_non_zero(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from slamkit.cli import main

    monkeypatch.setattr(
        LocalMapper, "step", _fail_on_call(8, "injected local-mapping failure")(LocalMapper.step), raising=True
    )
    out = tmp_path / "run"
    try:
        rc = main(["run", *BASE, f"hydra.run.dir={out}"])
    except SystemExit as exc:  # Hydra reports a task's exception and exits 1
        rc = int(exc.code or 0)
    assert rc != 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "failed" and metrics["failed_thread"] == "local-mapping"
    assert "injected local-mapping failure" in metrics["error"]
    poses = np.loadtxt(out / "trajectory.tum", ndmin=2)
    assert poses.shape[0] >= 10 and poses.shape[1] == 8


@pytest.mark.skipif(sys.platform == "win32", reason="SIGINT delivery to a child process is POSIX-only here")
def test_ctrl_c_stops_a_threaded_run_with_exit_code_130(tmp_path: Path) -> None:
    out = tmp_path / "run"
    cmd = [
        sys.executable,
        "-m",
        "slamkit.cli",
        "run",
        "runner=threaded",
        "runner.progress=false",
        f"hydra.run.dir={out}",
    ]
    # Ctrl-C once tracking runs on an initialised map
    returncode, output = interrupt_after(cmd, "map initialised", delay_s=3.0)
    assert returncode == 130, output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "interrupted"
    assert 0 < metrics["frames"] < 840
    assert np.loadtxt(out / "trajectory.tum", ndmin=2).shape[0] >= 1


def test_realtime_playback_drops_the_frames_tracking_is_too_busy_for() -> None:
    """At 8x the camera rate (240 Hz) the pipeline cannot keep up (the frame source's extraction ahead and tracking):
    tracking always takes the newest frame, the others are dropped and counted, and every frame is either tracked or
    dropped."""
    runner, dataset = _runner("runner.realtime=true", "runner.speed=8.0")
    log = runner.run(dataset, dataset.camera)
    assert log.frames_dropped > 0
    assert len(log.tracking) + log.frames_dropped == 150
    indices = [o.frame_index for o in log.tracking]
    assert indices == sorted(indices) and indices[-1] >= 140


def test_preloaded_realtime_playback_holds_every_frame_in_memory_and_restores_the_interpreter() -> None:
    """runner.preload reads every frame before the clock starts (memory reported); background threads run at a
    lower priority; the GIL switch interval is the configured one during the run and restored after it."""
    before = sys.getswitchinterval()
    runner, dataset = _runner(
        "runner.realtime=true",
        "runner.speed=8.0",
        "runner.preload=true",
        "runner.background_niceness=5",
        "runner.gil_switch_interval_ms=0.5",
    )
    seen_interval: list[float] = []
    log = runner.run(dataset, dataset.camera, on_frame=lambda out: seen_interval.append(sys.getswitchinterval()))
    # every frame holds its grey image (1 byte per pixel) and the synthetic depth map (float32, 4 bytes per pixel)
    assert log.preloaded_mb == pytest.approx(150 * 640 * 480 * (1 + 4) / 2**20)
    assert len(log.tracking) + log.frames_dropped == 150
    assert set(seen_interval) == {5e-4} and sys.getswitchinterval() == before
    assert runner._mapping is not None and runner._mapping.niceness == 5
    if sys.platform.startswith("linux"):
        assert runner._mapping.priority_lowered


@pytest.mark.parametrize("single", [False, True])
def test_realtime_extractions_ahead_stay_in_the_frame_source_thread_when_asked(
    single: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """runner.realtime_extract_single_threaded: in real time the frame source's extractions detect every pyramid
    level in its own thread (the extractor's level threads stay idle, leaving a core to local mapping); false: the
    level threads take part, as in tracking's own extraction."""
    runner, dataset = _runner(
        "runner.realtime=true",
        "runner.speed=8.0",
        "dataset.max_frames=30",
        "runner.realtime_extract_ahead=true",
        f"runner.realtime_extract_single_threaded={str(single).lower()}",
    )
    frontend: Any = runner.tracker.frontend  # the monocular front end (its ORB extractors: tracking's, the map's
    # initialisation's, both extracted ahead in real time)
    extractors = [frontend.extractor, frontend.init_extractor]
    assert all(extractor.n_threads >= 2 for extractor in extractors)
    # the pyramid levels detected during the frame source's extractions ahead, by thread: the front end's observe
    # called from the frame-source thread (ExtractedAhead.prepare calls it holding the front end's lock, which
    # tracking's own extractions take too: no other extraction runs meanwhile)
    threads: set[str] = set()
    preparing = threading.Event()
    observe = frontend.observe

    def spying(level_group: Any) -> Any:
        def spy(levels: list[int], pyramid: list[Any]) -> Any:
            if preparing.is_set():
                threads.add(threading.current_thread().name)
            return level_group(levels, pyramid)

        return spy

    def observed(*args: Any, **kwargs: Any) -> Any:
        if threading.current_thread().name != "frame-source":
            return observe(*args, **kwargs)
        preparing.set()
        try:
            return observe(*args, **kwargs)
        finally:
            preparing.clear()

    for extractor in extractors:
        monkeypatch.setattr(extractor, "_level_group", spying(extractor._level_group))
    monkeypatch.setattr(frontend, "observe", observed)
    log = runner.run(dataset, dataset.camera)
    assert len(log.tracking) + log.frames_dropped == 30
    assert "frame-source" in threads
    assert (threads == {"frame-source"}) == single  # false: the extractor's level threads took part


class _RecordedPlayback:
    """A dataset that records when it is prepared and when its frames start to be read."""

    def __init__(self, dataset: Any, events: list[str]) -> None:
        self.dataset, self.events = dataset, events

    def __getattr__(self, name: str) -> Any:
        return getattr(self.dataset, name)

    def __len__(self) -> int:
        return len(self.dataset)

    def prepare_playback(self) -> None:
        self.events.append("prepare")
        self.dataset.prepare_playback()

    def __iter__(self):  # type: ignore[no-untyped-def]
        self.events.append("iter")
        return iter(self.dataset)


def test_the_runner_prepares_the_dataset_and_warms_up_before_the_first_frame() -> None:
    """One-off costs (the synthetic world's textures, loading the compiled extraction kernels) are paid before
    the clock starts, and the warm-up leaves tracking where it was."""
    runner, dataset = _runner("runner.realtime=true", "runner.speed=8.0", "dataset.max_frames=30")
    events: list[str] = []
    real_warm_up = runner.tracker.warm_up

    def warm_up(camera: Any) -> None:
        events.append(f"warm up ({runner.tracker.state.value})")
        real_warm_up(camera)

    runner.tracker.warm_up = warm_up  # type: ignore[method-assign]
    log = runner.run(_RecordedPlayback(dataset, events), dataset.camera)
    assert events == ["prepare", "warm up (not_initialized)", "iter"]
    assert len(log.tracking) + log.frames_dropped == 30


def test_warm_up_leaves_the_tracker_untouched() -> None:
    runner, dataset = _runner()
    runner.tracker.warm_up(dataset.camera)
    assert runner.tracker.state.value == "not_initialized" and runner.tracker.init.reference is None
    assert runner.store.n_keyframes() == 0 and runner.store.n_points() == 0


def test_loop_detection_runs_without_parking_local_mapping(monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 13: loop closing looks at every keyframe while local mapping goes on; local mapping is parked only to
    correct an accepted loop (ORB-SLAM CorrectLoop: RequestStop), so it is parked exactly once per loop closed (the
    runner used to park it for every keyframe loop closing looked at). Every keyframe detection pinned is
    released."""
    pauses: list[str] = []
    real_pause = PipelineWorker.pause

    def counting_pause(self: PipelineWorker[Any], finish_queue: bool = False) -> Any:
        pauses.append(self.name)
        return real_pause(self, finish_queue)

    monkeypatch.setattr(PipelineWorker, "pause", counting_pause)
    runner, dataset = _runner()
    log = runner.run(dataset, dataset.camera)
    detections = [lp for lp in log.loops if lp.reason != "keyframe has no bag of words or was culled"]
    closed = sum(lp.loop_kf_id is not None for lp in log.loops)
    assert len(detections) >= 5, "loop closing looked at the keyframes"
    assert pauses.count("local-mapping") == runner.mapping_parks_for_loops == closed
    assert runner.loop_closer is not None
    assert runner.loop_closer.pins.total_pinned >= len(detections) and not runner.loop_closer.pins.snapshot()


@pytest.mark.parametrize("ahead_init", [True, False])
def test_realtime_extraction_ahead_of_a_monocular_initialisations_frames(ahead_init: bool) -> None:
    """``runner.realtime_extract_ahead_init`` (default false): in real time the frame source extracts the frames of a
    monocular initialisation ahead too, with the initialisation extractor (ORB-SLAM's 2x features), and tracking is
    served those records; false: tracking extracts them itself, as before."""
    runner, dataset = _runner(
        "runner.realtime=true", "dataset.max_frames=40", f"runner.realtime_extract_ahead_init={str(ahead_init).lower()}"
    )
    assert runner.realtime_extract_ahead_init is ahead_init
    served = _served_frames(runner)
    log = runner.run(dataset, dataset.camera)
    init_frames = [out for out in log.tracking if out.method == "initialize"]
    assert init_frames and any(out.initialized_map for out in init_frames)
    tracked = [out.n_features for out in log.tracking if out.method != "initialize"]
    # the initialisation extractor's records (pipeline.tracking.init_feature_factor 2: twice the features)
    assert tracked and min(out.n_features for out in init_frames) > max(tracked)
    served_init = [out.frame_index for out in init_frames if out.frame_index in served]
    if ahead_init:
        assert len(served_init) >= len(init_frames) - 1  # the first frame may come before the source's first
        assert all(out.timings_ms["extract_ms"] > 1.0 for out in init_frames if out.frame_index in served_init)
    else:
        assert served_init == []
