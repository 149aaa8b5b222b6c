"""Extraction ahead of tracking (slamkit/runtime/extract_ahead.py) with the room's real front end and ORB extractors:
a record made ahead is the one tracking would make, served once, never for a monocular initialisation's frames, and a
frame the front end cannot take fails where tracking extracts it."""

from __future__ import annotations

import dataclasses
import threading
from typing import Any

import numpy as np
import pytest

from slamkit.app import build_runner
from slamkit.config import compose_config
from slamkit.features import Observations
from slamkit.runtime.extract_ahead import ExtractedAhead


@pytest.fixture(scope="module")
def room() -> tuple[Any, Any]:
    runner, dataset = build_runner(
        compose_config(["runner=sequential", "runner.progress=false", "dataset.max_frames=6", "dataset.depth=false"])
    )
    return runner.tracker.frontend, dataset


def _same_record(a: Observations, b: Observations) -> None:
    for field in dataclasses.fields(a):
        x, y = getattr(a, field.name), getattr(b, field.name)
        if isinstance(x, np.ndarray):
            np.testing.assert_array_equal(x, y, err_msg=field.name)
        elif dataclasses.is_dataclass(x):
            _same_record(x, y)  # type: ignore[arg-type]
        else:
            assert x == y or (x != x and y != y), field.name  # NaN scalars compare equal here


def test_a_record_made_ahead_is_trackings_own_and_is_served_once(room: tuple[Any, Any]) -> None:
    frontend, dataset = room
    ahead = ExtractedAhead(frontend, dataset.camera)
    data = dataset[2]
    worker = threading.Thread(target=ahead.prepare, args=(data,))  # the frame source's thread
    worker.start()
    worker.join()
    assert ahead.extracted == 1
    served = ahead.observe(data, dataset.camera)
    assert ahead.served == 1 and len(served) > 500
    _same_record(served, frontend.observe(data, dataset.camera, False))
    ms = ahead.served_ms(2)
    assert ms is not None and ms > 0.0 and ahead.served_ms(2) is None  # reported once
    # taken once: the next request extracts again (a new, equal record)
    again = ahead.observe(data, dataset.camera)
    assert again is not served and ahead.served == 1
    _same_record(again, served)


def test_initialisation_frames_and_other_packets_are_extracted_by_tracking(room: tuple[Any, Any]) -> None:
    frontend, dataset = room
    ahead = ExtractedAhead(frontend, dataset.camera)
    data = dataset[3]
    ahead.prepare(data)
    init = ahead.observe(data, dataset.camera, initializing=True)  # ORB-SLAM's initialisation extractor: more features
    assert ahead.served == 0 and ahead.served_ms(3) is None
    _same_record(init, frontend.observe(data, dataset.camera, True))
    assert len(init) > len(frontend.observe(data, dataset.camera, False))
    # a record is for the packet it was made from: another packet with the same number is extracted anew
    ahead.prepare(data)
    other = dataclasses.replace(data, image=np.ascontiguousarray(data.image[::-1]))
    flipped = ahead.observe(other, dataset.camera)
    assert ahead.served == 0
    _same_record(flipped, frontend.observe(other, dataset.camera, False))
    # records of frames tracking has passed are let go
    ahead.prepare(dataset[4])
    ahead.observe(dataset[5], dataset.camera)
    assert ahead.observe(dataset[4], dataset.camera) is not None and ahead.served == 0


def test_the_trackers_hint_and_a_failing_frame(room: tuple[Any, Any]) -> None:
    frontend, dataset = room
    ahead = ExtractedAhead(frontend, dataset.camera, wanted=lambda d: d.index != 1)
    ahead.prepare(dataset[1])
    assert ahead.extracted == 0  # not wanted (tracking would use the initialisation extractor): not extracted
    bad = dataclasses.replace(dataset[1], image=np.zeros((7, 7), np.float32))
    ahead = ExtractedAhead(frontend, dataset.camera)
    ahead.prepare(bad)  # the frame source's thread does not fail
    assert ahead.extracted == 0
    with pytest.raises(Exception) as direct:
        frontend.observe(bad, dataset.camera, False)
    with pytest.raises(type(direct.value)):  # tracking meets the front end's own error for the frame
        ahead.observe(bad, dataset.camera)


class _GatedFrontEnd:
    """A front end whose extraction of one frame waits for a gate (an extraction under way in the frame source)."""

    def __init__(self, gated_index: int) -> None:
        self.gated_index = gated_index
        self.gate = threading.Event()
        self.entered = threading.Event()
        self.calls: list[int] = []

    def observe(self, data: Any, camera: Any, initializing: bool = False) -> Any:
        self.calls.append(data.index)
        if data.index == self.gated_index:
            self.entered.set()
            assert self.gate.wait(10.0)
        return ("record", data.index)


def test_a_ready_record_is_taken_while_a_later_frame_is_being_extracted() -> None:
    """Tracking takes frame 1's record at once while the frame source is still extracting frame 2 (before, the one
    lock around both made tracking wait for that extraction: on fr1_xyz 3.4 s of a 45 s run, p90 13 ms a frame)."""
    import types

    frontend = _GatedFrontEnd(gated_index=2)
    camera = object()
    ahead = ExtractedAhead(frontend, camera)  # type: ignore[arg-type]
    frames = {i: types.SimpleNamespace(index=i) for i in (1, 2)}
    ahead.prepare(frames[1])  # type: ignore[arg-type]
    source = threading.Thread(target=ahead.prepare, args=(frames[2],))
    source.start()
    assert frontend.entered.wait(10.0)  # frame 2's extraction is under way
    taken: list[Any] = []
    tracking = threading.Thread(target=lambda: taken.append(ahead.observe(frames[1], camera)))  # type: ignore[arg-type]
    tracking.start()
    tracking.join(5.0)
    try:
        assert not tracking.is_alive() and taken == [("record", 1)]
        # frame 2 itself: tracking waits for the extraction under way and takes its record (no second extraction)
        second: list[Any] = []
        waiting = threading.Thread(target=lambda: second.append(ahead.observe(frames[2], camera)))  # type: ignore[arg-type]
        waiting.start()
        waiting.join(0.2)
        assert waiting.is_alive()  # held until the extraction ends
    finally:
        frontend.gate.set()
        source.join(10.0)
    waiting.join(10.0)
    assert second == [("record", 2)] and frontend.calls == [1, 2] and ahead.served == 2


def test_single_threaded_extractions_ahead_stay_in_the_frame_source_thread(
    room: tuple[Any, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    """runner.extract_ahead_single_threaded: the ORB extractor's pyramid levels are all detected in the frame source's
    own thread (none in its level threads), and the record is the one the level threads give."""
    frontend, dataset = room
    extractor = frontend.extractor
    assert extractor.n_threads >= 2  # the room's default: the levels are shared out to worker threads
    ran_in: list[str] = []
    level_group = extractor._level_group

    def spy(levels: list[int], pyramid: list[Any]) -> Any:
        ran_in.append(threading.current_thread().name)
        return level_group(levels, pyramid)

    monkeypatch.setattr(extractor, "_level_group", spy)
    data = dataset[3]
    threads: dict[bool, set[str]] = {}
    records = {}
    for single in (False, True):
        ran_in.clear()
        ahead = ExtractedAhead(frontend, dataset.camera, single_threaded=single)
        source = threading.Thread(target=ahead.prepare, args=(data,), name="frame-source")
        source.start()
        source.join()
        records[single] = ahead.observe(data, dataset.camera)
        assert ahead.served == 1
        threads[single] = set(ran_in)
    assert threads[True] == {"frame-source"}
    assert "frame-source" in threads[False] and len(threads[False]) == 2  # the caller and one level thread
    _same_record(records[True], records[False])


def test_initialisation_frames_are_extracted_ahead_with_the_initialisation_extractor(room: tuple[Any, Any]) -> None:
    """``initialisation=True`` (real time): a frame the hint gives the initialisation extractor is extracted ahead with
    it and served only to a request for that extractor; without the flag such a frame is left to tracking."""
    frontend, dataset = room
    hint = lambda d: d.index != 2  # noqa: E731 - frame 2 gets the initialisation extractor (a map being initialised)
    ahead = ExtractedAhead(frontend, dataset.camera, wanted=hint, initialisation=True)
    data = dataset[2]
    ahead.prepare(data)
    assert ahead.extracted == 1
    served = ahead.observe(data, dataset.camera, initializing=True)
    assert ahead.served == 1 and ahead.served_ms(2) is not None
    direct = frontend.observe(data, dataset.camera, True)
    _same_record(served, direct)
    assert len(served) > len(frontend.observe(data, dataset.camera, False))  # the initialisation extractor's record
    # a record made with one extractor is never served to a request for the other
    ahead.prepare(data)
    tracked = ahead.observe(data, dataset.camera, initializing=False)
    assert ahead.served == 1
    _same_record(tracked, frontend.observe(data, dataset.camera, False))
    ahead.prepare(dataset[3])  # the tracking extractor's record (the hint), asked for with the other one
    again = ahead.observe(dataset[3], dataset.camera, initializing=True)
    assert ahead.served == 1
    _same_record(again, frontend.observe(dataset[3], dataset.camera, True))
    # without the flag a frame of an initialisation is not extracted ahead (as before)
    plain = ExtractedAhead(frontend, dataset.camera, wanted=hint)
    plain.prepare(data)
    assert plain.extracted == 0
