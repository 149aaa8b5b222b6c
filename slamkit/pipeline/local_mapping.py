"""Local mapping (ORB-SLAM sec. VI): keyframe insertion, recent map point culling, new point triangulation,
fusion of duplicates with the neighbours, local bundle adjustment, local keyframe culling.

``LocalMapper.step(keyframe)`` processes one keyframe. It takes the map's write lock for its edits and runs
the local BA on a snapshot without holding the lock (slamkit/pipeline/bundle.py).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from slamkit.geometry.se3 import invert_T
from slamkit.geometry.so3 import hat
from slamkit.geometry.twoview import triangulate_points
from slamkit.interfaces import AbortToken, Optimizer, PlaceRecognizer
from slamkit.map.entities import KeyFrame, MapPoint
from slamkit.map.store import InMemoryMapStore
from slamkit.pipeline.bundle import run_bundle, snapshot_bundle
from slamkit.pipeline.config import LocalMappingConfig
from slamkit.pipeline.fusion import fuse_points
from slamkit.pipeline.map_points import compute_distinctive_descriptor, update_normal_and_depth
from slamkit.pipeline.matching import hamming_matrix, resolve_one_to_one, rotation_consistent
from slamkit.pipeline.projection import project_pinhole

log = logging.getLogger("slamkit.mapping")

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: ORB-SLAM ORBmatcher TH_LOW: max Hamming distance for triangulation and fusion matches.
_TH_LOW = 50
#: Rotation-consistency histogram bins (ORB-SLAM HISTO_LENGTH).
_ROT_BINS = 30


@dataclass(frozen=True)
class CulledKeyFrame:
    """A keyframe removed by culling, kept as a pose relative to its spanning-tree parent so frames that
    referred to it can still be placed (ORB-SLAM keeps Tcp for the same reason)."""

    kf_id: int
    parent_id: int | None
    T_kf_parent: F64
    T_c_w: F64


@dataclass
class MappingOutcome:
    """What local mapping did with one keyframe (counts and per-stage times in ms)."""

    kf_id: int
    points_culled: int = 0
    points_created: int = 0
    points_fused: int = 0
    ba_outliers: int = 0
    ba_aborted: bool = False
    culled_keyframes: list[CulledKeyFrame] = field(default_factory=list)
    timings_ms: dict[str, float] = field(default_factory=dict)


def _keyframes(store: InMemoryMapStore, ids: Iterable[int]) -> dict[int, KeyFrame]:
    return {k: store.get_keyframe(k) for k in ids if store.has_keyframe(k)}


class LocalMapper:
    """Local mapping logic (deterministic: every loop runs in id order)."""

    def __init__(
        self,
        cfg: LocalMappingConfig,
        store: InMemoryMapStore,
        optimizer: Optimizer,
        place: PlaceRecognizer | None = None,
    ) -> None:
        self.cfg = cfg
        self.store = store
        self.optimizer = optimizer
        self.place = place  # describes each keyframe with a bag of words (ORB-SLAM ProcessNewKeyFrame)
        self.recent_points: list[int] = []

    def step(self, kf: KeyFrame, already_in_map: bool = False, abort: AbortToken | None = None) -> MappingOutcome:
        """Process one new keyframe (VI-A to VI-E)."""
        out = MappingOutcome(kf.id)
        t = time.perf_counter()

        def lap(name: str) -> None:
            nonlocal t
            now = time.perf_counter()
            out.timings_ms[name] = (now - t) * 1e3
            t = now

        with self.store.write():
            self._process_new_keyframe(kf, already_in_map)
            lap("insert_ms")
            out.points_culled = self._cull_recent_points(kf)
            lap("point_culling_ms")
            out.points_created = self._create_new_points(kf)
            lap("triangulation_ms")
            out.points_fused = self._search_in_neighbors(kf)
            lap("fusion_ms")
        if self.cfg.local_ba and self.store.n_keyframes() > 2 and not (abort is not None and abort.is_set()):
            out.ba_outliers, out.ba_aborted = self._local_bundle_adjustment(kf, abort)
        lap("local_ba_ms")
        if self.cfg.keyframe_culling:
            with self.store.write():
                out.culled_keyframes = self._cull_keyframes(kf)
        lap("keyframe_culling_ms")
        return out

    # ---- VI-A --------------------------------------------------------------------------------------

    def _process_new_keyframe(self, kf: KeyFrame, already_in_map: bool) -> None:
        store = self.store
        if self.place is not None and kf.bow is None:
            kf.bow = self.place.transform(kf.features.descriptors)
        if not already_in_map:
            store.add_keyframe(kf)
            for idx in np.flatnonzero(kf.point_ids >= 0):
                pid = int(kf.point_ids[idx])
                if not store.has_point(pid):
                    kf.point_ids[idx] = -1
                    continue
                point = store.get_point(pid)
                if kf.id in point.observations:  # two features of this keyframe matched the same point
                    kf.point_ids[idx] = -1
                    continue
                store.add_observation(pid, kf.id, int(idx))
                kfs = _keyframes(store, point.observations.keys())
                update_normal_and_depth(point, kfs)
                compute_distinctive_descriptor(point, kfs)
        store.update_connections(kf.id)

    # ---- VI-B --------------------------------------------------------------------------------------

    def _cull_recent_points(self, kf: KeyFrame) -> int:
        """Erase recent points found in fewer than 25% of the frames predicting them, or seen by fewer than
        three keyframes once past creation; points surviving three keyframes leave the recent list."""
        cfg = self.cfg
        culled = 0
        kept: list[int] = []
        for pid in self.recent_points:
            if not self.store.has_point(pid):
                continue
            point = self.store.get_point(pid)
            age = kf.id - point.first_kf_id
            if point.found_ratio() < cfg.point_min_found_ratio or (
                age >= cfg.point_culling_window_kfs - 1 and len(point.observations) < cfg.point_min_observations
            ):
                self.store.remove_point(pid)
                culled += 1
            elif age < cfg.point_culling_window_kfs:
                kept.append(pid)
        self.recent_points = kept
        return culled

    # ---- VI-C --------------------------------------------------------------------------------------

    def _create_new_points(self, kf: KeyFrame) -> int:
        """Triangulate unmatched features of the new keyframe with its covisible neighbours (VI-C)."""
        cfg = self.cfg
        store = self.store
        created = 0
        neighbors = store.covisibility.best_neighbors(kf.id, cfg.triangulation_neighbors)
        center1 = kf.center_w
        for n_id in neighbors:
            kf2 = store.get_keyframe(n_id)
            baseline = float(np.linalg.norm(kf2.center_w - center1))
            depths = _median_depth(kf2, store)
            if not np.isfinite(depths) or baseline / depths < cfg.min_baseline_depth_ratio:
                continue
            i1, i2 = self._match_for_triangulation(kf, kf2)
            if i1.size == 0:
                continue
            created += self._triangulate_and_add(kf, kf2, i1, i2)
        return created

    def _match_for_triangulation(self, kf1: KeyFrame, kf2: KeyFrame) -> tuple[I64, I64]:
        """Unmatched features of kf1 and kf2 with Hamming <= TH_LOW, on the epipolar line (distance^2 <
        3.84 sigma^2 of kf2's level), away from the epipole, best per feature, one-to-one, rotation-consistent
        (ORB-SLAM SearchForTriangulation; the candidates are all features instead of a BoW node's)."""
        f1 = np.flatnonzero(kf1.point_ids < 0)
        f2 = np.flatnonzero(kf2.point_ids < 0)
        if f1.size == 0 or f2.size == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        d = hamming_matrix(kf1.features.descriptors[f1], kf2.features.descriptors[f2])
        a, b = np.nonzero(d <= _TH_LOW)
        if a.size == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        uv1 = kf1.features.uv_undist_px[f1[a]].astype(np.float64)
        uv2 = kf2.features.uv_undist_px[f2[b]].astype(np.float64)
        F21 = _fundamental_21(kf1, kf2)
        lines = np.c_[uv1, np.ones(a.size)] @ F21.T  # epipolar lines in image 2
        num = np.einsum("ij,ij->i", lines, np.c_[uv2, np.ones(b.size)])
        dist2 = num**2 / np.maximum(lines[:, 0] ** 2 + lines[:, 1] ** 2, 1e-12)
        sigma2 = kf2.features.level_sigma2()[f2[b]]
        ok = dist2 < 3.84 * sigma2
        # ORB-SLAM: a candidate too close to the epipole cannot be triangulated reliably
        epipole = project_pinhole(kf2.T_c_w, kf1.center_w[None], kf2.camera.K)[0][0]
        scale2 = kf2.features.level_scale()[f2[b]]
        ok &= np.linalg.norm(uv2 - epipole, axis=1) >= 10.0 * scale2
        a, b, dd = a[ok], b[ok], d[a[ok], b[ok]]
        # best candidate per kf1 feature
        order = np.lexsort((b, dd, a))
        first = np.ones(order.size, bool)
        first[1:] = a[order][1:] != a[order][:-1]
        sel = order[first]
        a, b, dd = a[sel], b[sel], dd[sel]
        keep = resolve_one_to_one(a, b, dd)
        a, b = a[keep], b[keep]
        diff = kf1.features.angle_deg[f1[a]].astype(np.float64) - kf2.features.angle_deg[f2[b]]
        rot = rotation_consistent(diff, _ROT_BINS)
        return f1[a[rot]], f2[b[rot]]

    def _triangulate_and_add(self, kf1: KeyFrame, kf2: KeyFrame, i1: I64, i2: I64) -> int:
        cfg = self.cfg
        store = self.store
        K1, K2 = kf1.camera.K, kf2.camera.K
        uv1 = kf1.features.uv_undist_px[i1].astype(np.float64)
        uv2 = kf2.features.uv_undist_px[i2].astype(np.float64)
        rays1 = (np.c_[uv1, np.ones(i1.size)] @ np.linalg.inv(K1).T) @ kf1.T_c_w[:3, :3]
        rays2 = (np.c_[uv2, np.ones(i2.size)] @ np.linalg.inv(K2).T) @ kf2.T_c_w[:3, :3]
        cos_par = np.einsum("ij,ij->i", rays1, rays2) / (np.linalg.norm(rays1, axis=1) * np.linalg.norm(rays2, axis=1))
        ok = (cos_par > 0) & (cos_par < cfg.min_parallax_cos)
        xyz = triangulate_points(kf1.T_c_w, kf2.T_c_w, K1, K2, uv1, uv2)
        ok &= np.all(np.isfinite(xyz), axis=1)
        xyz = np.where(np.isfinite(xyz), xyz, 0.0)
        sigma1 = kf1.features.level_sigma2()[i1]
        sigma2 = kf2.features.level_sigma2()[i2]
        for T, K, uv, s2 in ((kf1.T_c_w, K1, uv1, sigma1), (kf2.T_c_w, K2, uv2, sigma2)):
            proj, z = project_pinhole(T, xyz, K)
            ok &= z > 0
            err2 = np.sum((np.where(np.isfinite(proj), proj, 1e9) - uv) ** 2, axis=1)
            ok &= err2 < cfg.chi2_mono * s2
        dist1 = np.linalg.norm(xyz - kf1.center_w, axis=1)
        dist2 = np.linalg.norm(xyz - kf2.center_w, axis=1)
        ok &= (dist1 > 0) & (dist2 > 0)
        ratio_dist = dist2 / np.maximum(dist1, 1e-12)
        ratio_octave = kf1.features.level_scale()[i1] / kf2.features.level_scale()[i2]
        factor = cfg.scale_consistency_factor * kf1.features.scale_factor
        ok &= ~((ratio_dist * factor < ratio_octave) | (ratio_dist > ratio_octave * factor))
        created = 0
        pair = _keyframes(store, {kf1.id, kf2.id})
        for m in np.flatnonzero(ok):
            a, b = int(i1[m]), int(i2[m])
            if kf1.point_ids[a] >= 0 or kf2.point_ids[b] >= 0:
                continue
            pid = store.new_point_id()
            point = MapPoint(pid, xyz[m].copy(), kf1.features.descriptors[a].copy(), kf1.id, kf1.id)
            store.add_point(point)
            store.add_observation(pid, kf1.id, a)
            store.add_observation(pid, kf2.id, b)
            compute_distinctive_descriptor(point, pair)
            update_normal_and_depth(point, pair)
            self.recent_points.append(pid)
            created += 1
        return created

    # ---- VI-D (fusion) -------------------------------------------------------------------------------

    def _search_in_neighbors(self, kf: KeyFrame) -> int:
        """Fuse the new keyframe's points into its neighbours (20 best + 5 of each) and theirs into it."""
        cfg = self.cfg
        store = self.store
        targets: list[int] = []
        seen = {kf.id}
        for n in store.covisibility.best_neighbors(kf.id, cfg.fuse_neighbors):
            if n not in seen:
                targets.append(n)
                seen.add(n)
        for n in list(targets):
            for n2 in store.covisibility.best_neighbors(n, cfg.fuse_second_neighbors):
                if n2 not in seen:
                    targets.append(n2)
                    seen.add(n2)
        fused = 0
        for t_id in targets:
            pids = [int(p) for p in kf.point_ids if p >= 0]
            fused += fuse_points(store, store.get_keyframe(t_id), pids, cfg.fuse_search_radius_px)
        candidates = sorted({int(p) for t_id in targets for p in store.get_keyframe(t_id).point_ids if p >= 0})
        fused += fuse_points(store, kf, candidates, cfg.fuse_search_radius_px)
        for pid in sorted({int(p) for p in kf.point_ids if p >= 0}):
            if store.has_point(pid):
                point = store.get_point(pid)
                kfs = _keyframes(store, point.observations.keys())
                compute_distinctive_descriptor(point, kfs)
                update_normal_and_depth(point, kfs)
        store.update_connections(kf.id)
        return fused

    # ---- VI-D (local BA) -----------------------------------------------------------------------------

    def _local_bundle_adjustment(self, kf: KeyFrame, abort: AbortToken | None) -> tuple[int, bool]:
        """Optimize the new keyframe, its covisible keyframes and all points they see; keyframes that see
        those points but are not covisible stay fixed (VI-D). The map's origin keyframe is always fixed."""
        store = self.store
        with store.read():
            local = [kf.id, *store.covisibility.neighbors(kf.id)]
            origin = min(store.keyframe_ids())
            free = [k for k in local if k != origin]
            pids = sorted({int(p) for k in local for p in store.get_keyframe(k).point_ids if p >= 0})
            fixed = sorted({o for p in pids for o in store.get_point(p).observations} - set(free))
            if not fixed and free:
                fixed = [free.pop(free.index(min(free)))]
            if not free or not pids:
                return 0, False
            cfg = self.cfg
            snap = snapshot_bundle(
                store,
                free,
                fixed,
                pids,
                cfg.ba_iterations_first,
                cfg.ba_iterations_second,
                cfg.ba_chi2_mono,
                cfg.ba_chi2_stereo,
            )
        result = run_bundle(store, self.optimizer, snap, abort)
        return int(result.outlier.sum()), bool(result.aborted)

    # ---- VI-E -------------------------------------------------------------------------------------------

    def _cull_keyframes(self, kf: KeyFrame) -> list[CulledKeyFrame]:
        """Erase covisible keyframes whose points are 90% seen by at least three other keyframes at the same
        or a finer scale (VI-E). The map's origin keyframe is never culled."""
        cfg = self.cfg
        store = self.store
        origin = min(store.keyframe_ids())
        culled: list[CulledKeyFrame] = []
        for k_id in store.covisibility.neighbors(kf.id):
            if k_id == origin or not store.has_keyframe(k_id):
                continue
            k = store.get_keyframe(k_id)
            n_points = 0
            redundant = 0
            for feat in np.flatnonzero(k.point_ids >= 0):
                pid = int(k.point_ids[feat])
                if not store.has_point(pid):
                    continue
                n_points += 1
                point = store.get_point(pid)
                if len(point.observations) <= cfg.keyframe_culling_min_observers:
                    continue
                level = int(k.features.level[feat])
                n_obs = 0
                for o_id, o_feat in point.observations.items():
                    if o_id == k_id:
                        continue
                    if int(store.get_keyframe(o_id).features.level[o_feat]) <= level + 1:
                        n_obs += 1
                        if n_obs >= cfg.keyframe_culling_min_observers:
                            break
                if n_obs >= cfg.keyframe_culling_min_observers:
                    redundant += 1
            if n_points and redundant > cfg.keyframe_culling_redundancy * n_points:
                parent = store.spanning_tree.parent.get(k_id)
                T_kp = k.T_c_w @ invert_T(store.get_keyframe(parent).T_c_w) if parent is not None else np.eye(4)
                culled.append(CulledKeyFrame(k_id, parent, T_kp, k.T_c_w.copy()))
                store.remove_keyframe(k_id)
                if self.place is not None:
                    self.place.remove(k_id)
        return culled


def _median_depth(kf: KeyFrame, store: InMemoryMapStore) -> float:
    pids = [int(p) for p in kf.point_ids if p >= 0 and store.has_point(int(p))]
    if not pids:
        return float("nan")
    xyz = np.stack([store.get_point(p).xyz_w for p in pids])
    return float(np.median(xyz @ kf.T_c_w[2, :3] + kf.T_c_w[2, 3]))


def _fundamental_21(kf1: KeyFrame, kf2: KeyFrame) -> F64:
    """F such that x2^T F x1 = 0 for undistorted pixels x1 in kf1 and x2 in kf2."""
    T21 = kf2.T_c_w @ invert_T(kf1.T_c_w)
    R21, t21 = T21[:3, :3], T21[:3, 3]
    E21 = hat(t21) @ R21
    return np.asarray(np.linalg.inv(kf2.camera.K).T @ E21 @ np.linalg.inv(kf1.camera.K))
