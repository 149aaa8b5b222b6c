"""Feature extraction ahead of tracking, in the frame-source thread (threaded runner, as fast as possible).

Played as fast as possible, the threaded runner's tracking thread waits for local mapping at every keyframe
(``runner.frame_waits_for``; docs/runtime.md): on fr1_xyz about 190 ms per keyframe, one keyframe every ~4 frames.
Before this module the frame's own ORB extraction (~9-12 ms, plus the image's decoding in the frame source) was the
only work that overlapped that wait. Here the frame-source thread, which already reads a few frames ahead, also
extracts their features (``FrontEnd.observe``, with the tracking extractor), so the tracking thread finds each frame's
observation record ready and the extraction runs on the core local mapping leaves idle.

Nothing the pipeline computes changes: a frame's record is what ``observe`` gives for it whichever thread runs it
(the extraction depends on the image and the extractor only), and a record is used only when tracking asks for the
extractor it was made with; a frame of a monocular initialisation (ORB-SLAM's bigger initialisation extractor) is
extracted by tracking, as before, unless ``initialisation`` (real time, ``runner.realtime_extract_ahead_init``): the
frame source then extracts such a frame with the initialisation extractor, and the record is served when tracking asks
for that one. The front end is called by one thread at a time (a lock): an extractor need not be thread-safe. The
records made are kept apart (a condition): tracking takes a ready record without waiting for the extraction ahead of a
later frame.

In real time (``runner.realtime_extract_ahead``) the frame source extracts each frame as it releases it, before the
one-slot mailbox, while tracking works on the frame before: the two threads then take a camera's frames as a two-stage
pipeline (docs/runtime.md). Not used for frames handed in by a caller (``ThreadedRunner.step``).
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from slamkit.features import Observations
from slamkit.interfaces import Camera, FrontEnd
from slamkit.sensors import FrameData
from slamkit.thread_budget import single_threaded

log = logging.getLogger("slamkit.runtime")


class ExtractedAhead:
    """Wraps a front end: ``prepare(data)`` (frame-source thread) extracts a frame's record ahead; ``observe``
    (tracking thread) returns it once, or extracts as the wrapped front end does when there is none for the frame or
    tracking asks for the initialisation extractor's. Every other attribute is the wrapped front end's.

    wanted: whether a frame read now is worth extracting ahead (the tracker's hint: not while it initialises a map,
    whose frames get the initialisation extractor; a wrong hint costs time only, never a different record).
    initialisation: a frame the hint says tracking would extract with the initialisation extractor is extracted ahead
    with that one (``observe(..., initializing=True)``) rather than left to tracking; each record is served only to a
    request for the extractor it was made with. Worth it in real time, where the frame source extracts the one frame
    tracking takes next (a wrong guess, at the frame that completes an initialisation, wastes one extraction); false:
    as before, the initialisation's frames are extracted by tracking.
    single_threaded: run the extractions ahead inside ``slamkit.thread_budget.single_threaded`` (an extractor's own
    worker threads, such as the ORB extractor's level threads, are not used; the records are the same).
    """

    def __init__(
        self,
        frontend: FrontEnd,
        camera: Camera,
        wanted: Callable[[FrameData], bool] | None = None,
        single_threaded: bool = False,
        initialisation: bool = False,
    ) -> None:
        self.frontend = frontend
        self.initialisation = bool(initialisation)
        self.camera = camera
        self._wanted = wanted
        # extractions ahead keep their work in the frame-source thread (slamkit.thread_budget): beside a busy local
        # mapping thread, an extractor's own worker threads would take its core
        self.single_threaded = single_threaded
        self._frontend_lock = threading.Lock()  # one extraction at a time: the front end's extractors are not shared
        self._cond = threading.Condition()  # guards _ready and _in_flight (never held during an extraction)
        # frame index -> (packet, record, ms, made with the initialisation extractor)
        self._ready: dict[int, tuple[FrameData, Observations, float, bool]] = {}
        self._in_flight: int | None = None  # the frame being extracted ahead now
        self._served_ms: dict[int, float] = {}  # frames whose record came from ahead -> its extraction's ms
        self.extracted = 0  # records made ahead
        self.served = 0  # records tracking took from ahead

    def prepare(self, data: FrameData) -> None:
        """Extract ``data``'s record now (frame-source thread). A failure is left to tracking, which extracts the
        frame itself and meets the error where a frame's failure belongs (its frame number, the run's outputs)."""
        initializing = self._wanted is not None and not self._wanted(data)
        if initializing and not self.initialisation:
            return
        with self._cond:
            self._in_flight = data.index
        made: tuple[FrameData, Observations, float, bool] | None = None
        try:
            with self._frontend_lock, single_threaded() if self.single_threaded else contextlib.nullcontext():
                t0 = time.perf_counter()
                record = self.frontend.observe(data, self.camera, initializing)
                made = (data, record, (time.perf_counter() - t0) * 1e3, initializing)
        except Exception as exc:  # tracking extracts this frame itself and reports the error there
            log.debug("frame %d: extraction ahead failed (%s); tracking extracts it", data.index, exc)
        finally:
            with self._cond:
                self._in_flight = None
                if made is not None:
                    self._ready[data.index] = made
                    self.extracted += 1
                self._cond.notify_all()

    def observe(self, data: FrameData, camera: Camera, initializing: bool = False) -> Observations:
        """The record of ``data``: the one extracted ahead (taken once) when it was made for this packet and camera
        with the extractor asked for (``initializing``), else the wrapped front end's ``observe``. A ready record is
        taken without waiting for the extraction ahead of a later frame (the front end's lock guards extractions only);
        a frame whose own extraction ahead is under way is waited for rather than extracted twice."""
        with self._cond:
            while self._in_flight == data.index:
                self._cond.wait()
            ready = self._ready.pop(data.index, None)
            # frames tracking has passed (skipped, or asked with the initialisation extractor) are never asked again
            for index in [i for i in self._ready if i < data.index]:
                del self._ready[index]
        if ready is not None and ready[0] is data and camera is self.camera and ready[3] == bool(initializing):
            self._served_ms[data.index] = ready[2]
            self.served += 1
            return ready[1]
        with self._frontend_lock:
            return self.frontend.observe(data, camera, initializing)

    def served_ms(self, frame_index: int) -> float | None:
        """The extraction time (ms, in the frame-source thread) of the record ``observe`` served ahead for this frame,
        once; None when tracking extracted the frame itself."""
        return self._served_ms.pop(frame_index, None)

    def __getattr__(self, name: str) -> Any:
        # n_levels, scale_factor, warm_up, uses_depth, bind_dataset, extractor, ...: the wrapped front end's
        return getattr(self.frontend, name)
