"""The lifecycle-event dispatcher: delivery order and thread, isolation of a failing listener, a critical
listener's failure, and the hook specifications it fires."""

from __future__ import annotations

import dataclasses
import logging
import threading

import numpy as np
import pluggy
import pytest

from slamkit import hookspecs
from slamkit.errors import PluginError
from slamkit.events import MapSnapshot, PointsCulled, RunFinished
from slamkit.hookspecs import hookimpl
from slamkit.runtime.events import LIFECYCLE_HOOKS, EventDispatcher


class Recorder:
    """Records every points_culled event it gets and the thread it got it on."""

    def __init__(self, fail_at: int | None = None) -> None:
        self.got: list[int] = []
        self.threads: set[str] = set()
        self.fail_at = fail_at

    @hookimpl
    def slamkit_points_culled(self, event: PointsCulled) -> None:
        self.got.append(event.kf_id)
        self.threads.add(threading.current_thread().name)
        if self.fail_at is not None and event.kf_id == self.fail_at:
            raise ValueError(f"listener broke at keyframe {event.kf_id}")


def manager(**plugins: object) -> pluggy.PluginManager:
    pm = pluggy.PluginManager(hookspecs.PROJECT_NAME)
    pm.add_hookspecs(hookspecs.SlamkitHookSpecs)
    for name, plugin in plugins.items():
        pm.register(plugin, name=name)
    return pm


def culled(kf_id: int) -> PointsCulled:
    return PointsCulled(run_id=1, map_id=0, kf_id=kf_id, n_points=3)


def test_every_lifecycle_hook_has_a_spec_prefixed_slamkit() -> None:
    pm = manager()
    for name in LIFECYCLE_HOOKS:
        assert name.startswith("slamkit_") and getattr(pm.hook, name).spec is not None, name


@pytest.mark.parametrize("threaded", [False, True])
def test_events_reach_listeners_in_order_inline_or_on_the_dispatcher_thread(threaded: bool) -> None:
    rec = Recorder()
    dispatcher = EventDispatcher(manager(rec=rec).hook)
    dispatcher.start(threaded)
    for k in range(200):
        dispatcher.emit("slamkit_points_culled", culled(k))
    dispatcher.close()  # delivers everything queued before returning
    assert rec.got == list(range(200))
    assert rec.threads == ({"lifecycle-events"} if threaded else {threading.current_thread().name})


@pytest.mark.parametrize("threaded", [False, True])
def test_a_failing_listener_is_logged_by_name_dropped_and_others_go_on(
    threaded: bool, caplog: pytest.LogCaptureFixture
) -> None:
    broken, good = Recorder(fail_at=3), Recorder()
    dispatcher = EventDispatcher(manager(viewer=broken, logger=good).hook)
    dispatcher.start(threaded)
    with caplog.at_level(logging.ERROR, logger="slamkit.events"):
        for k in range(10):
            dispatcher.emit("slamkit_points_culled", culled(k))
        dispatcher.close()  # no error: the listener was not critical
    assert broken.got == [0, 1, 2, 3]
    assert good.got == list(range(10))
    assert "plugin 'viewer' failed in slamkit_points_culled" in caplog.text
    assert "listener broke at keyframe 3" in caplog.text


@pytest.mark.parametrize("threaded", [False, True])
def test_a_critical_listener_failure_is_raised_when_the_run_ends(threaded: bool) -> None:
    dispatcher = EventDispatcher(manager(outputs=Recorder(fail_at=1)).hook, critical={"outputs"})
    dispatcher.start(threaded)
    for k in range(3):
        dispatcher.emit("slamkit_points_culled", culled(k))
    with pytest.raises(PluginError, match=r"plugin 'outputs'.*slamkit_points_culled.*listener broke at keyframe 1"):
        dispatcher.close()


def test_a_critical_failure_is_only_logged_when_the_run_failed_already(caplog: pytest.LogCaptureFixture) -> None:
    dispatcher = EventDispatcher(manager(outputs=Recorder(fail_at=0)).hook, critical={"outputs"})
    dispatcher.start(threaded=False)
    dispatcher.emit("slamkit_points_culled", culled(0))
    with caplog.at_level(logging.ERROR, logger="slamkit.events"):
        dispatcher.close(raise_critical=False)
    assert "plugin 'outputs' (the run's outputs) failed" in caplog.text


def test_without_listeners_nothing_is_wanted_and_no_thread_starts() -> None:
    dispatcher = EventDispatcher(manager().hook)
    assert not any(dispatcher.wants(name) for name in LIFECYCLE_HOOKS)
    before = threading.active_count()
    dispatcher.start(threaded=True)
    dispatcher.emit("slamkit_points_culled", culled(0))
    assert threading.active_count() == before
    dispatcher.close()
    assert not EventDispatcher(None).wants("slamkit_frame_tracked")


def test_events_are_frozen_plain_data() -> None:
    snap = MapSnapshot(0, np.array([2, 5]), np.array([0.5, 0.1]), np.zeros((2, 4, 4)), np.zeros((2, 4, 4)), 7)
    event = RunFinished(1, "ok", None, None, (snap,), 0, 1.0, 1.0, 0, 1.0, 0.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        event.status = "failed"  # type: ignore[misc]
    assert snap.n_keyframes == 2 and snap.keyframe_timestamps() == {2: 0.5, 5: 0.1}
