"""Recording the camera trajectory as ORB-SLAM does: each tracked frame's pose relative to its reference
keyframe, so the final trajectory follows every later correction of the keyframes (BA, loop closing)."""

from __future__ import annotations

from collections.abc import Collection, Mapping
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from slamkit.geometry.se3 import invert_T
from slamkit.interfaces import MapStore
from slamkit.pipeline.outcomes import CulledKeyFrame
from slamkit.sensors import Trajectory

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class _Record:
    frame_index: int
    timestamp_s: float
    ref_kf_id: int
    T_c_r: F64


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

    def frames(self, store: MapStore) -> Trajectory:
        """Every recorded frame's pose T_w_c (frames whose keyframe cannot be resolved are left out)."""
        return self.frames_at({k: store.get_keyframe(k).T_c_w for k in store.keyframe_ids()})

    def frames_at(self, keyframe_poses: Mapping[int, F64]) -> Trajectory:
        """Every recorded frame's pose T_w_c, given the map's keyframes' current poses (kf_id -> (4, 4) T_c_w;
        frames whose keyframe cannot be resolved are left out)."""
        t, poses = [], []
        for rec in self._records:
            T_r_w = self._keyframe_pose(keyframe_poses, rec.ref_kf_id)
            if T_r_w is None:
                continue
            t.append(rec.timestamp_s)
            poses.append(invert_T(rec.T_c_r @ T_r_w))
        if not poses:
            return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
        return Trajectory(np.array(t), np.stack(poses))

    @staticmethod
    def keyframes(store: MapStore) -> Trajectory:
        """The map's keyframes, T_w_c in time order."""
        kfs = sorted((store.get_keyframe(k) for k in store.keyframe_ids()), key=lambda k: k.timestamp_s)
        if not kfs:
            return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
        return Trajectory(np.array([k.timestamp_s for k in kfs]), np.stack([k.T_w_c for k in kfs]))
