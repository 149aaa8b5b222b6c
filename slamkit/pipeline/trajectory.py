"""Recording the camera trajectory as ORB-SLAM does: each tracked frame's pose relative to its reference
keyframe, so the final trajectory follows every later correction of the keyframes (BA, loop closing).

A map file keeps a map's frames the same way (``export``: FrameRecords, culled references resolved), and a later
session's recorders start from them (``load``): its trajectory then holds every session's frames, placed against the
keyframes as that session left them (docs/atlas.md, "Multi-session")."""

from __future__ import annotations

from collections.abc import Collection, Mapping
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from slamkit.geometry.se3 import invert_T
from slamkit.interfaces import MapStore
from slamkit.map.atlas import MapChange
from slamkit.pipeline.outcomes import CulledKeyFrame
from slamkit.sensors import FrameRecords, Trajectory

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class _Record:
    frame_index: int
    timestamp_s: float
    ref_kf_id: int
    T_c_r: F64
    loaded: bool = False  # a frame of an earlier session, read from a map file (``load``)


class TrajectoryRecorder:
    """Collects tracked frames; ``frames(store)`` resolves them against the keyframes' current poses."""

    def __init__(self) -> None:
        self._records: list[_Record] = []
        self._culled: dict[int, CulledKeyFrame] = {}

    def __len__(self) -> int:
        return len(self._records)

    def clear(self) -> None:
        """Forget everything (the map was reset: earlier poses live in a map that no longer exists)."""
        self._records.clear()
        self._culled.clear()

    def take(self) -> TrajectoryRecorder:
        """A recorder with this one's frames and culled keyframes; this one is left empty (the active map changed:
        the runner keeps the old map's frames apart)."""
        out = TrajectoryRecorder()
        out._records, out._culled = self._records, self._culled
        self._records, self._culled = [], {}
        return out

    def load(self, records: FrameRecords) -> None:
        """Add the frames of earlier sessions (a map file's, slamkit/map/mapfile.py), each relative to a keyframe of
        this recorder's map; the frames stay in time order (stable: equal times keep loaded frames first)."""
        loaded = [
            _Record(int(i), float(t), int(r), np.array(T, np.float64), loaded=True)
            for i, t, r, T in zip(records.frame_index, records.t_s, records.ref_kf_id, records.T_c_r, strict=True)
        ]
        if not loaded:
            return
        self._records = loaded + self._records
        self._records.sort(key=lambda rec: rec.timestamp_s)

    def export(self, keyframe_ids: Collection[int]) -> FrameRecords:
        """The recorded frames (loaded ones included) as a map file keeps them: each relative to a keyframe of
        ``keyframe_ids`` (the map's keyframes now). A frame whose reference keyframe was culled is re-expressed
        relative to the first keyframe up the culled keyframes' parents that is still in the map, by composing the
        relative poses known when they were culled (T_c_p = T_c_r @ T_r_p, ORB-SLAM's SaveTrajectoryTUM follows
        the spanning tree the same way); a frame that resolves to no keyframe of the map is left out."""
        live = set(keyframe_ids)
        t, index, ref, poses = [], [], [], []
        for rec in self._records:
            kf_id, T = rec.ref_kf_id, rec.T_c_r
            for _ in range(10_000):
                if kf_id in live:
                    break
                culled = self._culled.get(kf_id)
                if culled is None or culled.parent_id is None:
                    break
                T = T @ culled.T_kf_parent
                kf_id = culled.parent_id
            if kf_id not in live:
                continue
            t.append(rec.timestamp_s)
            index.append(rec.frame_index)
            ref.append(kf_id)
            poses.append(T)
        if not t:
            return FrameRecords.empty()
        return FrameRecords(
            np.array(t, np.float64), np.array(index, np.int64), np.array(ref, np.int64), np.stack(poses)
        )

    def record(self, frame_index: int, timestamp_s: float, T_c_w: F64, ref_kf_id: int, T_ref_w: F64) -> None:
        self._records.append(_Record(frame_index, timestamp_s, ref_kf_id, T_c_w @ invert_T(T_ref_w)))

    def record_relative(self, frame_index: int, timestamp_s: float, ref_kf_id: int, T_c_r: F64) -> None:
        """Record a frame by its pose relative to its reference keyframe, (4, 4) T_c_r = T_c_w @ T_w_r."""
        self._records.append(_Record(frame_index, timestamp_s, ref_kf_id, T_c_r))

    def on_culled(self, culled: CulledKeyFrame) -> None:
        self._culled[culled.kf_id] = culled

    def _live(self, kf_id: int) -> int:
        """The keyframe a record's reference resolves to: ``kf_id`` itself, or the first keyframe up its culled
        parents that was not culled."""
        for _ in range(10_000):
            culled = self._culled.get(kf_id)
            if culled is None or culled.parent_id is None:
                return kf_id
            kf_id = culled.parent_id
        return kf_id

    def rescale(self, moved_kf_ids: Collection[int] | None, scale: float) -> None:
        """A map merge moved the keyframes ``moved_kf_ids`` (None: every keyframe recorded here) by a similarity of
        scale ``scale`` (slamkit/pipeline/map_merging.py): the frames recorded relative to them (directly or through
        culled keyframes) and those culled keyframes' poses relative to their parents get their translations scaled,
        so they stay where they were relative to the moved keyframes (a rigid move leaves relative poses as they
        are; its scale does not)."""
        if scale == 1.0:
            return
        for i in range(len(self._records)):  # tracking may append meanwhile (threaded runner): by index
            rec = self._records[i]
            if moved_kf_ids is None or self._live(rec.ref_kf_id) in moved_kf_ids:
                T = rec.T_c_r.copy()
                T[:3, 3] *= scale
                self._records[i] = replace(rec, T_c_r=T)
        for kf_id, culled in list(self._culled.items()):
            if moved_kf_ids is None or self._live(kf_id) in moved_kf_ids:
                T = culled.T_kf_parent.copy()
                T[:3, 3] *= scale
                self._culled[kf_id] = replace(culled, T_kf_parent=T)

    def absorb(self, other: TrajectoryRecorder) -> None:
        """Take over another recorder's frames and culled keyframes (its map was merged into this one's); the frames
        stay in time order (the absorbed map's are usually the earlier ones: a trajectory file's timestamps must not
        decrease)."""
        self._records.extend(other._records)
        self._records.sort(key=lambda rec: rec.timestamp_s)  # stable: equal times keep their order
        self._culled.update(other._culled)

    def _keyframe_pose(self, keyframe_poses: Mapping[int, F64], kf_id: int, depth: int = 0) -> F64 | None:
        """Current T_c_w of a keyframe, following culled keyframes to their parents."""
        pose = keyframe_poses.get(kf_id)
        if pose is not None:
            return pose
        culled = self._culled.get(kf_id)
        if culled is None:
            return None
        if culled.parent_id is None or depth > 10_000:
            return culled.T_c_w
        parent = self._keyframe_pose(keyframe_poses, culled.parent_id, depth + 1)
        return culled.T_c_w if parent is None else culled.T_kf_parent @ parent

    def frames(self, store: MapStore, loaded: bool = True) -> Trajectory:
        """Every recorded frame's pose T_w_c (frames whose keyframe cannot be resolved are left out; loaded: with
        the earlier sessions' frames ``load`` added)."""
        return self.frames_at({k: store.get_keyframe(k).T_c_w for k in store.keyframe_ids()}, loaded)

    def frames_at(self, keyframe_poses: Mapping[int, F64], loaded: bool = True) -> Trajectory:
        """Every recorded frame's pose T_w_c, given the map's keyframes' current poses (kf_id -> (4, 4) T_c_w;
        frames whose keyframe cannot be resolved are left out). loaded: with the earlier sessions' frames (``load``;
        False: this run's frames only)."""
        t, poses = [], []
        for rec in self._records:
            if rec.loaded and not loaded:
                continue
            T_r_w = self._keyframe_pose(keyframe_poses, rec.ref_kf_id)
            if T_r_w is None:
                continue
            t.append(rec.timestamp_s)
            poses.append(invert_T(rec.T_c_r @ T_r_w))
        if not poses:
            return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
        times, T_w_c = np.array(t), np.stack(poses)
        if loaded and any(rec.loaded for rec in self._records):
            # this run's frames come after the loaded ones in the list, and two sessions' times may overlap: time order
            order = np.argsort(times, kind="stable")
            times, T_w_c = times[order], T_w_c[order]
        return Trajectory(times, T_w_c)

    @staticmethod
    def keyframes(store: MapStore) -> Trajectory:
        """The map's keyframes, T_w_c in time order."""
        kfs = sorted((store.get_keyframe(k) for k in store.keyframe_ids()), key=lambda k: k.timestamp_s)
        if not kfs:
            return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
        return Trajectory(np.array([k.timestamp_s for k in kfs]), np.stack([k.T_w_c for k in kfs]))


class KeptFrames:
    """The frames of the Atlas's maps that a runner's ``recorder`` (this run's frames in the active map since it
    became active) does not hold, kept so that a map file written at the end holds every frame of every map (a
    runner's ``map_frames``; docs/atlas.md, "Multi-session"): the frames a map file kept for its maps (earlier
    sessions), those of a map left for a new one (tracking lost), and those of a map absorbed by a merge. It follows
    the same events as the recorder: culled keyframes of the active map, a merge's move and absorption, a reset.

    Keyed by map id; each value a list of recorders (each in time order; ``export`` joins them)."""

    def __init__(self, loaded: Mapping[int, FrameRecords]) -> None:
        self._maps: dict[int, list[TrajectoryRecorder]] = {}
        for map_id, records in loaded.items():
            recorder = TrajectoryRecorder()
            recorder.load(records)
            self._maps[map_id] = [recorder]

    def map_changed(self, change: MapChange | None, map_before: int, recorder: TrajectoryRecorder) -> None:
        """The active map changed after a frame (``Atlas.change_since``; None: it did not): a map left
        for a new one keeps ``recorder``'s frames (taken from it: it starts again empty), a reset map loses its
        frames (its keyframes were erased)."""
        if change is None:
            return
        if change == MapChange.NEW_MAP:
            self._maps.setdefault(map_before, []).append(recorder.take())
        else:
            recorder.clear()
            self._maps.pop(map_before, None)

    def on_culled(self, map_id: int, culled: CulledKeyFrame) -> None:
        """A keyframe of map ``map_id`` was culled: frames of an earlier session may have it as their reference."""
        for recorder in self._maps.get(map_id, ()):
            recorder.on_culled(culled)

    def merged(self, into_map_id: int, merged_map_id: int, moved_kf_ids: Collection[int] | None, scale: float) -> None:
        """A merge moved the map ``into_map_id`` (its keyframes ``moved_kf_ids``, by a similarity of scale
        ``scale``) and absorbed ``merged_map_id``: the frames kept for the moved map follow the move's scale, the
        absorbed map's frames now belong to the moved one."""
        for recorder in self._maps.get(into_map_id, ()):
            recorder.rescale(moved_kf_ids, scale)
        absorbed = self._maps.pop(merged_map_id, [])
        if absorbed:
            self._maps.setdefault(into_map_id, []).extend(absorbed)

    def export(
        self, keyframe_ids: Mapping[int, Collection[int]], active_id: int, recorder: TrajectoryRecorder
    ) -> dict[int, FrameRecords]:
        """map id -> every frame of that map as a map file keeps it (``TrajectoryRecorder.export``), for the maps of
        ``keyframe_ids`` (map id -> its keyframe ids now); the active map's include ``recorder``'s."""
        out: dict[int, FrameRecords] = {}
        for map_id, kf_ids in keyframe_ids.items():
            parts = [*self._maps.get(map_id, ()), *([recorder] if map_id == active_id else [])]
            joined = TrajectoryRecorder()
            for part in parts:
                joined.absorb(part)
            out[map_id] = joined.export(kf_ids)
        return out
