"""Per-frame and per-keyframe timeline of a run, for comparing the threaded and the sequential runner (issue 14).

Usage: nice -n 19 python benchmarks/keyframe_timeline.py OUT.json -- run runner=threaded seed=0 [overrides...]

Runs ``slamkit`` with the arguments after ``--`` and records, without changing what the run does:

- every tracked frame: index, timestamp (s), the local-mapping state tracking was given (idle, and whether the
  threaded runner would wait for it), the keyframe decision, the keyframes made, map points tracked (inliers), the
  time tracking waited for local mapping (ms), and whether local mapping was processing a keyframe while the frame
  was tracked (``lm_busy``: the frame saw a map local mapping had not finished); where the keyframe decision ran,
  its numbers (ORB-SLAM2 NeedNewKeyFrame): ``tracked`` (mnMatchesInliers), ``n_ref`` (the reference
  keyframe's nRefMatches, None when the reference is not in the map), ``ref``, ``c1a``, ``c1b``, ``c2``, the last
  keyframe tracking made (``last_kf``), whether local mapping has inserted it (``last_kf_in_map``) and whether it is
  the reference (``ref_is_last_kf``); while it is not inserted, ``n_ref_if_last_kf_in_map``: its nRefMatches as if
  it were (its own observation added to its points');
- every keyframe local mapping processed: its id, whether the abort token was already set when local mapping took
  it (``abort_at_start``) and when local BA would start (``abort_before_ba``: local BA skipped), whether local BA
  ran and was aborted, points created / fused, keyframes culled, and the stage timings (ms);

then writes OUT.json ({"frames": [...], "keyframes": [...]}) and prints a summary: keyframes made, frames tracked
while local mapping was busy, local BAs run / skipped / aborted, keyframes culled, the frames between keyframes.
The run's outputs (trajectory.tum, keyframes.tum, metrics.json) are written as by ``slamkit run``.
"""

from __future__ import annotations

import atexit
import json
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np

import slamkit.pipeline.local_mapping as local_mapping
import slamkit.pipeline.tracking.tracker as tracker_mod
from slamkit.cli import main as slamkit_main

frames: list[dict[str, Any]] = []
keyframes: list[dict[str, Any]] = []
#: the keyframe decision's numbers of each frame it ran on (Tracker._keyframe_facts), merged into its ``frames`` row
decision_facts: list[dict[str, Any]] = []
_lm_busy = threading.Event()  # local mapping is inside LocalMapper.step
#: local mapping's stage now: "idle", "insert" (ProcessNewKeyFrame and point culling), "triangulation", "fusion",
#: "after_fusion" (no local BA, or keyframe culling without one), "local_ba" (local BA, then keyframe culling), and
#: the keyframe it works on
_lm_stage: dict[str, Any] = {"stage": "idle", "kf": None}


def summarize() -> str:
    """What the timeline says, in a few lines."""
    made = [f for f in frames if f["n_new_kf"] > 0]
    kf_frames = [f["frame"] for f in made]
    gaps = np.diff(kf_frames) if len(kf_frames) > 1 else np.zeros(0)
    tracked_busy = sum(1 for f in frames if f["lm_busy"])
    waited = [f["wait_ms"] for f in frames if f["wait_ms"] > 0]
    ba_run = sum(1 for k in keyframes if k["ba_ran"])
    ba_skipped = sum(1 for k in keyframes if not k["ba_ran"] and k["n_kf_in_map"] > 2)
    ba_aborted = sum(1 for k in keyframes if k["ba_aborted"])
    culled = sum(k["culled"] for k in keyframes)
    decisions: dict[str, int] = {}
    for f in frames:
        decisions[f["decision"]] = decisions.get(f["decision"], 0) + 1
    return "\n".join(
        [
            f"frames {len(frames)}, keyframes made {sum(f['n_new_kf'] for f in frames)} at {len(made)} frames, "
            f"processed {len(keyframes)}, culled {culled}",
            f"frames between keyframes: median {np.median(gaps) if gaps.size else float('nan'):.1f}, "
            f"mean {gaps.mean() if gaps.size else float('nan'):.2f}",
            f"frames tracked while local mapping was busy: {tracked_busy}; frames that waited for it: {len(waited)} "
            f"(median {np.median(waited) if waited else 0:.0f} ms)",
            f"local BA: ran {ba_run} (aborted {ba_aborted}), skipped {ba_skipped}; abort set when a keyframe was "
            f"taken: {sum(1 for k in keyframes if k['abort_at_start'])}, before its BA: "
            f"{sum(1 for k in keyframes if k['abort_before_ba'])}",
            f"decisions: {decisions}",
            f"inliers median {np.median([f['inliers'] for f in frames]):.0f}",
        ]
    )


def main(argv: list[str]) -> None:
    if len(argv) < 3 or argv[1] != "--":
        raise SystemExit(__doc__)
    out = Path(argv[0])

    step = tracker_mod.Tracker.step

    def traced_step(self: Any, data: Any, camera: Any, mapping: Any = None) -> Any:
        busy = _lm_busy.is_set()
        n_facts = len(decision_facts)
        if callable(mapping):  # read by the tracker once the frame's features are extracted
            lazy = mapping
            given: list[Any] = []

            def mapping_now() -> Any:
                given.append(lazy())
                return given[-1]

            outcome = step(self, data, camera, mapping_now)
            mapping = given[-1] if given else None
        else:
            outcome = step(self, data, camera, mapping)
        facts = decision_facts[n_facts] if len(decision_facts) > n_facts else {}
        frames.append(
            {
                "frame": outcome.frame_index,
                "t": outcome.timestamp_s,
                "state": outcome.state.value,
                "idle": None if mapping is None else bool(mapping.idle),
                "waits": None if mapping is None else bool(getattr(mapping, "waits_for_idle", False)),
                "decision": outcome.keyframe.value,
                "n_new_kf": len(outcome.new_keyframes),
                "inliers": outcome.inliers,
                "lm_busy": busy or _lm_busy.is_set(),
                "wait_ms": 0.0,
                **facts,
            }
        )
        return outcome

    tracker_mod.Tracker.step = traced_step  # type: ignore[method-assign]

    new_kf = tracker_mod.Tracker._new_keyframe
    last_kf: dict[str, Any] = {}

    def traced_new_kf(self: Any, frame: Any) -> Any:
        kf = new_kf(self, frame)
        last_kf["kf"] = kf
        return kf

    tracker_mod.Tracker._new_keyframe = traced_new_kf  # type: ignore[method-assign]

    kf_facts = tracker_mod.Tracker._keyframe_facts

    def traced_facts(self: Any, frame: Any, inliers: int, mapping: Any) -> Any:
        facts = kf_facts(self, frame, inliers, mapping)
        cfg = self.cfg
        store = self.store
        kf = last_kf.get("kf")
        row: dict[str, Any] = {
            "tracked": facts.tracked_points,
            "n_ref": facts.reference_tracked_points,
            "ref": self.reference_kf_id,
            "n_kfs": facts.keyframes_in_map,
            "c1a": facts.frame_index >= facts.last_keyframe_frame_index + facts.max_frames,
            "c1b": bool(facts.mapping.idle or facts.mapping.waits_for_idle),
            "lm_stage": _lm_stage["stage"],
            "lm_kf": _lm_stage["kf"],
        }
        ref = facts.reference_tracked_points
        row["c2"] = bool(
            (ref is None or facts.tracked_points < cfg.keyframe_max_ref_ratio * ref)
            and facts.tracked_points > cfg.keyframe_min_tracked_points
        )
        with store.read():
            row["last_kf"] = None if kf is None else kf.id
            row["last_kf_in_map"] = kf is not None and store.has_keyframe(kf.id)
            row["ref_is_last_kf"] = kf is not None and self.reference_kf_id == kf.id
            if kf is not None and not row["last_kf_in_map"]:
                # the last keyframe's count as if local mapping had inserted it (its own observation added)
                ids = kf.point_ids[kf.point_ids >= 0]
                ids = ids[store.has_points(ids)]
                n_obs = store.point_rows(ids, "n_observations") + 1 if ids.size else np.zeros(0, np.int64)
                need = tracker_mod.reference_min_observations(facts.keyframes_in_map + 1, cfg)
                row["n_ref_if_last_kf_in_map"] = int(np.count_nonzero(n_obs >= need))
        decision_facts.append(row)
        return facts

    tracker_mod.Tracker._keyframe_facts = traced_facts  # type: ignore[method-assign]

    make = tracker_mod.Tracker.make_keyframe

    def traced_make(self: Any, outcome: Any) -> Any:
        result = make(self, outcome)
        if frames and frames[-1]["frame"] == result.frame_index:
            frames[-1]["n_new_kf"] = len(result.new_keyframes)
            frames[-1]["decision"] = "insert_after_wait"
        return result

    tracker_mod.Tracker.make_keyframe = traced_make  # type: ignore[method-assign]

    lm_step = local_mapping.LocalMapper.step
    lba = local_mapping.LocalMapper._local_bundle_adjustment
    current: dict[str, Any] = {}

    def traced_lba(self: Any, kf: Any, abort: Any) -> Any:
        current["ba_ran"] = True
        _lm_stage["stage"] = "local_ba"
        return lba(self, kf, abort)

    def traced_lm_step(self: Any, kf: Any, abort: Any = None) -> Any:
        _lm_busy.set()
        _lm_stage.update(stage="insert", kf=kf.id)
        current.clear()
        current["ba_ran"] = False
        at_start = abort is not None and abort.is_set()
        cnp = self._create_new_points

        def traced_cnp(kf_: Any, abort_: Any = None) -> Any:
            _lm_stage["stage"] = "triangulation"
            n = cnp(kf_, abort_)
            current["abort_after_tri"] = abort_ is not None and abort_.is_set()
            return n

        self._create_new_points = traced_cnp
        fusion = self._search_in_neighbors

        def traced_fusion(kf_: Any) -> Any:
            _lm_stage["stage"] = "fusion"
            n = fusion(kf_)
            current["abort_before_ba"] = abort is not None and abort.is_set()
            _lm_stage["stage"] = "after_fusion"
            return n

        self._search_in_neighbors = traced_fusion
        try:
            outcome = lm_step(self, kf, abort)
        finally:
            del self._create_new_points, self._search_in_neighbors
            _lm_busy.clear()
            _lm_stage.update(stage="idle", kf=None)
        keyframes.append(
            {
                "kf": outcome.kf_id,
                "n_kf_in_map": self.store.n_keyframes(),
                "abort_at_start": at_start,
                "abort_after_tri": current.get("abort_after_tri", False),
                "abort_before_ba": current.get("abort_before_ba", False),
                "ba_ran": current["ba_ran"],
                "ba_aborted": outcome.ba_aborted,
                "created": outcome.points_created,
                "fused": outcome.points_fused,
                "culled": len(outcome.culled_keyframes),
                "timings_ms": dict(outcome.timings_ms),
            }
        )
        return outcome

    local_mapping.LocalMapper._local_bundle_adjustment = traced_lba  # type: ignore[method-assign]
    local_mapping.LocalMapper.step = traced_lm_step  # type: ignore[method-assign]

    try:
        import slamkit.runtime.threaded as threaded

        track = threaded.ThreadedRunner._track

        def traced_track(self: Any, data: Any, camera: Any) -> Any:
            result = track(self, data, camera)
            if frames and frames[-1]["frame"] == result.frame_index:
                frames[-1]["wait_ms"] = float(result.timings_ms.get("mapping_wait_ms", 0.0))
            return result

        threaded.ThreadedRunner._track = traced_track  # type: ignore[method-assign]
    except AttributeError:
        pass

    def write() -> None:
        out.write_text(json.dumps({"frames": frames, "keyframes": keyframes}))
        print(summarize())

    atexit.register(write)
    sys.argv = ["slamkit", *argv[2:]]
    slamkit_main()


if __name__ == "__main__":
    main(sys.argv[1:])
