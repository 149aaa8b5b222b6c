"""Local mapping (ORB-SLAM sec. VI): keyframe insertion, recent map point culling, new point triangulation,
fusion of duplicates with the neighbours, local bundle adjustment, local keyframe culling.

``LocalMapper.step(keyframe)`` processes one keyframe. It takes the map's write lock for its edits and runs
the local BA on a snapshot without holding the lock (slamkit/pipeline/bundle.py).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from contextlib import nullcontext

import numpy as np
from numpy.typing import NDArray

from slamkit.features import Features
from slamkit.geometry.camera import PinholeCamera
from slamkit.geometry.se3 import invert_T
from slamkit.geometry.so3 import hat
from slamkit.geometry.twoview import triangulate_points
from slamkit.interfaces import AbortToken, Camera, MapStore, Optimizer, PlaceRecognizer
from slamkit.map.atlas import Atlas
from slamkit.map.entities import KeyFrame
from slamkit.pipeline.bundle import run_bundle, snapshot_bundle
from slamkit.pipeline.config import LocalMappingConfig
from slamkit.pipeline.frame import keyframe_cameras, keyframe_view
from slamkit.pipeline.fusion import KeyFramePoints, fuse_points
from slamkit.pipeline.keyframe_culling import ObservationTable
from slamkit.pipeline.keyframe_insertion import insert_keyframe
from slamkit.pipeline.keyframe_pins import KeyFramePins
from slamkit.pipeline.map_points import (
    add_observations,
    add_points,
    create_depth_points,
    gather_observations,
    new_pair_points,
    orbslam_observation_counts,
    refresh_points,
    unique_point_ids,
)
from slamkit.pipeline.matching import close_pairs, resolve_one_to_one, rotation_consistent
from slamkit.pipeline.outcomes import CulledKeyFrame, MappingOutcome
from slamkit.pipeline.projection import project_points, require_pinhole_image
from slamkit.pipeline.triangulation_kernels import epipolar_candidates, parallax_ok, triangulated_ok

log = logging.getLogger("slamkit.mapping")

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: the point id marking, in the scratch copy of a keyframe triangulation plans with, a feature already given a new point
_PLANNED = np.iinfo(np.int64).max


class LocalMapper:
    """Local mapping logic (deterministic: every loop runs in id order)."""

    def __init__(
        self,
        cfg: LocalMappingConfig,
        atlas: Atlas,
        optimizer: Optimizer,
        place: PlaceRecognizer | None = None,
        pins: KeyFramePins | None = None,
    ) -> None:
        """pins: keyframes loop closing is using (its ``LoopCloser.pins``), which keyframe culling leaves."""
        self.cfg = cfg
        self.pins = pins if pins is not None else KeyFramePins()
        self.atlas = atlas  # the maps; local mapping works on the active one (``store``)
        self.optimizer = optimizer
        self.place = place  # describes each keyframe with a bag of words (ORB-SLAM ProcessNewKeyFrame)
        self.recent_points: list[int] = []
        # (keyframe id, its point ids (sorted), their observation counts) right after insertion's refresh of them:
        # fusion's closing refresh recomputes only the points whose observations changed since (_changed_points)
        self._inserted: tuple[int, I64, I64] | None = None

    @property
    def store(self) -> MapStore:
        """The active map of the Atlas."""
        return self.atlas.active

    def step(self, kf: KeyFrame, abort: AbortToken | None = None) -> MappingOutcome:
        """Process one new keyframe (VI-A to VI-E): one tracking made, or one of the two of a new map."""
        out = MappingOutcome(kf.id)
        t = time.perf_counter()

        def lap(name: str) -> None:
            nonlocal t
            now = time.perf_counter()
            out.timings_ms[name] = (now - t) * 1e3
            t = now

        # The write lock is taken per mutation phase (never across the matching, triangulation or BA work) so a
        # tracking thread is held up for short spells only.
        with self.store.write():
            self._process_new_keyframe(kf)
        lap("insert_ms")
        with self.store.write():
            out.points_culled = self._cull_recent_points(kf)
        lap("point_culling_ms")
        out.points_created = self._create_new_points(kf, abort)
        lap("triangulation_ms")
        out.points_fused = self._search_in_neighbors(kf)
        lap("fusion_ms")
        out.ba_due = self.cfg.local_ba and self.store.n_keyframes() > 2
        out.ba_skipped = out.ba_due and abort is not None and abort.is_set()
        if out.ba_due and not out.ba_skipped:
            out.ba_outliers, out.ba_aborted = self._local_bundle_adjustment(kf, abort)
        lap("local_ba_ms")
        if self.cfg.keyframe_culling:
            with self.store.write():
                out.culled_keyframes = self._cull_keyframes(kf, abort)
        lap("keyframe_culling_ms")
        return out

    # ---- VI-A --------------------------------------------------------------------------------------

    def _process_new_keyframe(self, kf: KeyFrame) -> None:
        """ORB-SLAM ProcessNewKeyFrame: insert the keyframe (a no-op for the keyframes of a new map, which
        initialisation inserted), describe it with a bag of words, update its covisibility connections. With
        ``new_map_points_culled`` (``new_map_points_culled_stereo`` for a stereo/RGB-D keyframe), the points a keyframe
        of a new map was created with (it observes them already: ORB-SLAM's ``IsInKeyFrame`` branch) join the recent
        points that VI-B's culling checks."""
        store = self.store
        cull_own = self.cfg.new_map_points_culled_stereo if kf.features.bf > 0.0 else self.cfg.new_map_points_culled
        inserted = insert_keyframe(store, kf)
        self._inserted = (kf.id, *_observation_counts(store, kf.point_ids)) if inserted else None
        if not inserted and cull_own:
            own = store.get_keyframe(kf.id).point_ids
            own = own[own >= 0]
            known = set(self.recent_points)
            self.recent_points.extend(p for p in own[store.has_points(own)].tolist() if p not in known)
        if kf.features.bf > 0.0:
            self.recent_points.extend(create_depth_points(store, kf, self.cfg.stereo_new_points_min))
        if self.place is not None and kf.bow is None:
            store.set_keyframe_bow(kf.id, self.place.transform(kf.features.descriptors))
        store.update_connections(kf.id)

    # ---- VI-B --------------------------------------------------------------------------------------

    def _cull_recent_points(self, kf: KeyFrame) -> int:
        """Erase recent points found in fewer than 25% of the frames predicting them, or seen by fewer than
        three keyframes once past creation; points surviving three keyframes leave the recent list."""
        cfg = self.cfg
        store = self.store
        culled = 0
        kept: list[int] = []
        alive = [pid for pid in self.recent_points if store.has_point(pid)]
        ids = np.array(alive, np.int64)
        found_ratio = (
            store.point_rows(ids, "n_found") / np.maximum(store.point_rows(ids, "n_visible"), 1)
            if ids.size
            else np.zeros(0)
        )
        stereo = kf.features.bf > 0.0
        # stereo/RGB-D: ORB-SLAM2 MapPointCulling's cnThObs = 3 on Observations(), which counts a stereo observation
        # twice; monocular: fewer than point_min_observations keyframes (cnThObs = 2)
        n_obs = orbslam_observation_counts(store, alive) if stereo else None
        for i, pid in enumerate(alive):
            point = store.get_point(pid)
            age = kf.id - point.first_kf_id
            too_few = (
                n_obs[i] <= cfg.point_culling_max_observations_stereo
                if n_obs is not None
                else len(point.observations) < cfg.point_min_observations
            )
            if found_ratio[i] < cfg.point_min_found_ratio or (age >= cfg.point_culling_window_kfs - 1 and too_few):
                store.remove_point(pid)
                culled += 1
            elif age < cfg.point_culling_window_kfs:
                kept.append(pid)
        self.recent_points = kept
        return culled

    # ---- VI-C --------------------------------------------------------------------------------------

    def _create_new_points(self, kf: KeyFrame, abort: AbortToken | None = None) -> int:
        """Triangulate unmatched features of the new keyframe with its covisible neighbours (VI-C).

        Stops after the first neighbour once ``abort`` is set — a newer keyframe waits (ORB-SLAM2 CreateNewMapPoints:
        ``if(i>0 && CheckNewKeyFrames()) return;``; the runners set the token when they hand local mapping a
        keyframe while it works). Each neighbour's matching and triangulation run under the read lock; the new points of
        all the neighbours are then added at once under the write lock (planned again there, for the same neighbours,
        if a loop correction bumped the map's epoch in between). A neighbour's plan sees the features of ``kf`` that
        the neighbours before it took as matched, so the points are those of adding each neighbour's in turn."""
        store = self.store
        with store.read():
            nn = self.cfg.triangulation_neighbors_stereo if kf.features.bf > 0.0 else self.cfg.triangulation_neighbors
            neighbors = store.covisibility.best_neighbors(kf.id, nn)
            epoch = store.epoch
        planned, visited = self._plan_new_points(kf, neighbors, abort, read_lock=True)
        with store.write():
            if store.epoch != epoch:
                planned, _ = self._plan_new_points(kf, neighbors[:visited], None, read_lock=False)
            return self._add_points(kf, planned)

    def _plan_new_points(
        self, kf: KeyFrame, neighbors: list[int], abort: AbortToken | None, read_lock: bool
    ) -> tuple[list[tuple[KeyFrame, I64, I64, F64]], int]:
        """The new points of ``kf`` with each neighbour in turn (``_triangulate_with``, then the pairs ``_free_pairs``
        gives a point), each neighbour under the read lock when ``read_lock``; a scratch copy of ``kf`` marks the
        features taken by the neighbours before (the map is not changed). -> ([(neighbour, features of kf (S,), of the
        neighbour (S,), (S, 3) world points m)], the number of neighbours visited before ``abort`` stopped the loop)."""
        store = self.store
        planned: list[tuple[KeyFrame, I64, I64, F64]] = []
        view = kf  # kf with the features planned so far marked as matched
        visited = 0
        for i, n_id in enumerate(neighbors):
            if i > 0 and abort is not None and abort.is_set():
                break
            visited += 1
            with store.read() if read_lock else nullcontext():
                found = self._triangulate_with(view, n_id)
                if found is None:
                    continue
                kf2 = store.get_keyframe(n_id)
                i1, i2, xyz = found
                sel = _free_pairs(view, kf2, i1, i2)
            if not sel.size:
                continue
            planned.append((kf2, i1[sel], i2[sel], xyz[sel]))
            marked = np.array(view.point_ids)
            marked[i1[sel]] = _PLANNED
            view = dataclasses.replace(view, point_ids=marked)
        return planned, visited

    def _triangulate_with(self, kf: KeyFrame, n_id: int) -> tuple[I64, I64, F64] | None:
        """(features of kf, features of the neighbour, (M, 3) m world points) that pass VI-C's checks, or None
        when the neighbour is gone, too close for its scene depth, or gives nothing. Reads the map only."""
        store = self.store
        if not store.has_keyframe(n_id) or not store.has_keyframe(kf.id):
            return None
        kf2 = store.get_keyframe(n_id)
        baseline = float(np.linalg.norm(kf2.center_w - kf.center_w))
        depths = _median_depth(kf2, store)
        if not np.isfinite(depths) or baseline / depths < self.cfg.min_baseline_depth_ratio:
            return None
        if not (kf.features.two_cameras or kf2.features.two_cameras):
            i1, i2 = self._match_for_triangulation(kf, kf2)
            if i1.size == 0:
                return None
            return self._triangulate(kf, kf2, i1, i2)
        # two-camera keyframes (ORB-SLAM3 CreateNewMapPoints with mpCamera2): each keypoint through its own camera,
        # every pair of cameras searched; a keypoint taken by an earlier pair is skipped when the points are added
        found: list[tuple[I64, I64, F64]] = []
        for c1 in keyframe_cameras(kf):
            for c2 in keyframe_cameras(kf2):
                v1, v2 = keyframe_view(kf, c1), keyframe_view(kf2, c2)
                i1, i2 = self._match_for_triangulation(v1, v2, c1, c2)
                if i1.size == 0:
                    continue
                tri = self._triangulate(v1, v2, i1, i2)
                if tri is not None:
                    found.append(tri)
        if not found:
            return None
        return (
            np.concatenate([f[0] for f in found]),
            np.concatenate([f[1] for f in found]),
            np.concatenate([f[2] for f in found]),
        )

    def _match_for_triangulation(
        self, kf1: KeyFrame, kf2: KeyFrame, camera_1: int = 0, camera_2: int = 0
    ) -> tuple[I64, I64]:
        """Unmatched features of kf1 and kf2 with Hamming <= TH_LOW, on the epipolar line (distance^2 <
        3.84 sigma^2 of kf2's level, pipeline.chi2.epipolar), away from the epipole, best per feature,
        one-to-one, rotation-consistent (ORB-SLAM SearchForTriangulation; thresholds from pipeline.matcher). As
        ORB-SLAM, the candidates are those the place recognizer pairs (``PlaceRecognizer.candidate_pairs``: DBoW
        compares only features under the same vocabulary node) when both keyframes have a bag of words;
        otherwise every pair is a candidate. camera_1 / camera_2: the camera of each keyframe whose keypoints are
        searched (two-camera keyframes: ``kf1`` / ``kf2`` are then that camera's views, :func:`~slamkit.pipeline.frame.keyframe_view`)."""
        empty = np.zeros(0, np.int64), np.zeros(0, np.int64)
        matcher = self.cfg.matcher
        free1 = kf1.point_ids < 0
        free2 = kf2.point_ids < 0
        # two-camera keyframes: the searched camera's keypoints whose stereo partner has no point either (the partner's
        # point stands for both)
        free1 &= _camera_free(kf1, camera_1)
        free2 &= _camera_free(kf2, camera_2)
        if not free1.any() or not free2.any():
            return empty
        if self.place is not None and kf1.bow is not None and kf2.bow is not None:
            a, b, d = self.place.candidate_pairs(
                kf1.features, kf1.bow, kf2.features, kf2.bow, free1, free2, max_distance=matcher.th_low
            )
        else:
            a, b, d = close_pairs(kf1.features.descriptors, kf2.features.descriptors, free1, free2, matcher.th_low)
        if a.size == 0:
            return empty
        uv1 = _pinhole_uv(kf1, a)
        uv2 = _pinhole_uv(kf2, b)
        F21 = _fundamental_21(kf1, kf2)
        if not (kf1.features.two_cameras or kf2.features.two_cameras):
            # one compiled pass: the epipolar distance and the epipole test below, for one-camera keyframes
            epipole = _epipole(kf1, kf2)
            ok = epipolar_candidates(
                uv1,
                uv2,
                F21,
                _level_sigma2(kf2.features, b),
                self.cfg.chi2.epipolar,
                True,
                np.ascontiguousarray(epipole, np.float64),
                _level_scale(kf2.features, b),
                matcher.epipole_min_dist2,
                np.isfinite(kf1.features.u_right_px[a]) | np.isfinite(kf2.features.u_right_px[b]),
            )
            return self._select_matches(kf1, kf2, a[ok], b[ok], d[ok])
        lines = np.c_[uv1, np.ones(a.size)] @ F21.T  # epipolar lines in image 2
        num = np.einsum("ij,ij->i", lines, np.c_[uv2, np.ones(b.size)])
        dist2 = num**2 / np.maximum(lines[:, 0] ** 2 + lines[:, 1] ** 2, 1e-12)
        sigma2 = _level_sigma2(kf2.features, b)
        ok = dist2 < self.cfg.chi2.epipolar * sigma2
        # ORB-SLAM: a candidate too close to the epipole cannot be triangulated reliably: squared distance below
        # epipole_min_dist2 x the scale factor of its level (not squared, as ORB-SLAM writes it). An epipole at
        # infinity (kf1's centre level with kf2's image plane) is close to nothing: NaN distances are not rejected.
        if not (kf1.features.two_cameras or kf2.features.two_cameras):
            # ORB-SLAM3 SearchForTriangulation checks the epipole for one-camera keyframes only (!pKF1->mpCamera2)
            epipole = project_points(kf2.T_c_w, kf1.center_w[None], kf2.camera)[0][0]
            scale2 = _level_scale(kf2.features, b)
            with np.errstate(invalid="ignore"):
                near_epipole = np.sum((uv2 - epipole) ** 2, axis=1) < matcher.epipole_min_dist2 * scale2
            # ORB-SLAM2/3 SearchForTriangulation: `if(!bStereo1 && !bStereo2)`: only a pair without a right coordinate
            # on either side is refused near the epipole (a stereo keypoint can be made from its depth)
            near_epipole &= ~(np.isfinite(kf1.features.u_right_px[a]) | np.isfinite(kf2.features.u_right_px[b]))
            ok &= ~near_epipole
        return self._select_matches(kf1, kf2, a[ok], b[ok], d[ok])

    def _select_matches(self, kf1: KeyFrame, kf2: KeyFrame, a: I64, b: I64, dd: I64) -> tuple[I64, I64]:
        """The candidates (a, b, Hamming distance dd) (K,) that passed the epipolar tests -> the best per kf1 feature,
        one-to-one, rotation-consistent (ORB-SLAM SearchForTriangulation's last steps)."""
        matcher = self.cfg.matcher
        # best candidate per kf1 feature
        order = np.lexsort((b, dd, a))
        first = np.ones(order.size, bool)
        first[1:] = a[order][1:] != a[order][:-1]
        sel = order[first]
        a, b, dd = a[sel], b[sel], dd[sel]
        keep = resolve_one_to_one(a, b, dd)
        a, b = a[keep], b[keep]
        diff = kf1.features.angle_deg[a].astype(np.float64) - kf2.features.angle_deg[b]
        rot = rotation_consistent(diff, matcher.rotation_bins)
        return a[rot], b[rot]

    def _triangulate(self, kf1: KeyFrame, kf2: KeyFrame, i1: I64, i2: I64) -> tuple[I64, I64, F64] | None:
        """Triangulate matched features; keep those with enough parallax, in front of both cameras, within the
        chi-square reprojection gate in both, and scale-consistent (VI-C)."""
        cfg = self.cfg
        K1, K2 = kf1.camera.K, kf2.camera.K
        uv1 = _pinhole_uv(kf1, i1)
        uv2 = _pinhole_uv(kf2, i2)
        stereo = kf1.features.bf > 0.0 or kf2.features.bf > 0.0
        if not stereo and _pinhole_one_camera(kf1) and _pinhole_one_camera(kf2):
            return self._triangulate_mono(kf1, kf2, i1, i2, uv1, uv2)
        rays1 = (np.c_[uv1, np.ones(i1.size)] @ np.linalg.inv(K1).T) @ kf1.T_c_w[:3, :3]
        rays2 = (np.c_[uv2, np.ones(i2.size)] @ np.linalg.inv(K2).T) @ kf2.T_c_w[:3, :3]
        cos_par = np.einsum("ij,ij->i", rays1, rays2) / (np.linalg.norm(rays1, axis=1) * np.linalg.norm(rays2, axis=1))
        if stereo:
            ok, xyz = _triangulate_with_depths(kf1, kf2, i1, i2, uv1, uv2, cos_par, cfg.min_parallax_cos)
        else:
            ok = (cos_par > 0) & (cos_par < cfg.min_parallax_cos)
            xyz = triangulate_points(kf1.T_c_w, kf2.T_c_w, K1, K2, uv1, uv2)
        ok &= np.all(np.isfinite(xyz), axis=1)
        xyz = np.where(np.isfinite(xyz), xyz, 0.0)
        sigma1 = _level_sigma2(kf1.features, i1)
        sigma2 = _level_sigma2(kf2.features, i2)
        for kf, idx, s2 in ((kf1, i1, sigma1), (kf2, i2, sigma2)):
            uv = kf.features.uv_undist_px[idx].astype(np.float64)  # the keypoint in its camera's pipeline image
            proj, z, _ = project_points(kf.T_c_w, xyz, kf.camera)
            ok &= z > 0
            err2 = np.sum((np.where(np.isfinite(proj), proj, 1e9) - uv) ** 2, axis=1)
            if not stereo:
                ok &= err2 < cfg.chi2.mono * s2
                continue
            # ORB-SLAM2 CreateNewMapPoints: a keypoint with a right coordinate is checked in 3 dof (gate 7.8)
            ur = kf.features.u_right_px[idx].astype(np.float64)
            has_ur = np.isfinite(ur)
            z_safe = np.where(z > 0, z, 1.0)
            err_r = np.where(
                has_ur, np.where(np.isfinite(proj[:, 0]), proj[:, 0], 1e9) - kf.features.bf / z_safe - ur, 0
            )
            ok &= np.where(has_ur, err2 + err_r**2 < cfg.chi2.stereo_rounded * s2, err2 < cfg.chi2.mono * s2)
        dist1 = np.linalg.norm(xyz - kf1.center_w, axis=1)
        dist2 = np.linalg.norm(xyz - kf2.center_w, axis=1)
        ok &= (dist1 > 0) & (dist2 > 0)
        ratio_dist = dist2 / np.maximum(dist1, 1e-12)
        ratio_octave = _level_scale(kf1.features, i1) / _level_scale(kf2.features, i2)
        factor = cfg.scale_consistency_factor * kf1.features.scale_factor
        ok &= ~((ratio_dist * factor < ratio_octave) | (ratio_dist > ratio_octave * factor))
        if not ok.any():
            return None
        return i1[ok], i2[ok], xyz[ok]

    def _triangulate_mono(
        self, kf1: KeyFrame, kf2: KeyFrame, i1: I64, i2: I64, uv1: F64, uv2: F64
    ) -> tuple[I64, I64, F64] | None:
        """:meth:`_triangulate` for two monocular one-camera keyframes with pinhole images (uv1 / uv2 (M, 2) their
        undistorted px) in two compiled passes: the parallax test before the DLT (only its survivors are
        triangulated: the DLT solves each pair on its own), the other tests after."""
        cfg = self.cfg
        K1, K2 = kf1.camera.K, kf2.camera.K
        T1, T2 = kf1.T_c_w, kf2.T_c_w
        par = parallax_ok(
            uv1,
            uv2,
            _inverse_K(kf1.camera),
            _inverse_K(kf2.camera),
            np.ascontiguousarray(T1[:3, :3]),
            np.ascontiguousarray(T2[:3, :3]),
            cfg.min_parallax_cos,
        )
        sel = np.flatnonzero(par)
        if not sel.size:
            return None
        i1, i2, uv1, uv2 = i1[sel], i2[sel], uv1[sel], uv2[sel]
        xyz = triangulate_points(T1, T2, K1, K2, uv1, uv2)
        f1, f2 = kf1.features, kf2.features
        ok = triangulated_ok(
            xyz,
            uv1,
            uv2,
            np.ascontiguousarray(T1, np.float64),
            np.ascontiguousarray(T2, np.float64),
            _pinhole_intrinsics(kf1),
            _pinhole_intrinsics(kf2),
            cfg.chi2.mono * _level_sigma2(f1, i1),
            cfg.chi2.mono * _level_sigma2(f2, i2),
            np.ascontiguousarray(kf1.center_w, np.float64),
            np.ascontiguousarray(kf2.center_w, np.float64),
            _level_scale(f1, i1) / _level_scale(f2, i2),
            cfg.scale_consistency_factor * f1.scale_factor,
        )
        if not ok.any():
            return None
        return i1[ok], i2[ok], xyz[ok]

    def _add_points(self, kf1: KeyFrame, planned: list[tuple[KeyFrame, I64, I64, F64]]) -> int:
        """Add the planned new points (new map points, VI-C): for each (kf2, feat1 (S,), feat2 (S,), xyz (S, 3) world
        m) of ``_plan_new_points`` in order, S points each observed by feature feat1[q] of kf1 and feat2[q] of kf2.

        The ids are drawn in that order and the points written at once (map_points.add_points / add_observations):
        the map is the one the neighbours' points added one neighbour after the other leave."""
        store = self.store
        planned = [p for p in planned if p[1].size]
        if not planned:
            return 0
        created = np.array([store.new_point_id() for _ in range(sum(p[1].size for p in planned))], np.int64)
        bounds = np.cumsum([0, *(p[1].size for p in planned)])
        points = []
        for (kf2, feat1, feat2, xyz), lo, hi in zip(planned, bounds[:-1], bounds[1:], strict=True):
            # refresh_points(store, created) folded into the points' making: each is seen by (kf1, a) and (kf2, b) only
            points.extend(new_pair_points(created[lo:hi], xyz, kf1, feat1, kf2, feat2))
        add_points(store, points)
        add_observations(store, created, kf1.id, np.concatenate([p[1] for p in planned]))
        for (kf2, _, feat2, _), lo, hi in zip(planned, bounds[:-1], bounds[1:], strict=True):
            add_observations(store, created[lo:hi], kf2.id, feat2)
        self.recent_points.extend(created.tolist())
        return int(created.size)

    # ---- VI-D (fusion) -------------------------------------------------------------------------------

    def _search_in_neighbors(self, kf: KeyFrame) -> int:
        """Fuse the new keyframe's points into its neighbours (20 best + 5 of each) and theirs into it."""
        cfg = self.cfg
        store = self.store
        targets: list[int] = []
        seen = {kf.id}
        with store.read():
            nn = cfg.fuse_neighbors_stereo if kf.features.bf > 0.0 else cfg.fuse_neighbors
            for n in store.covisibility.best_neighbors(kf.id, nn):
                if n not in seen:
                    targets.append(n)
                    seen.add(n)
            for n in list(targets):
                for n2 in store.covisibility.best_neighbors(n, cfg.fuse_second_neighbors):
                    if n2 not in seen:
                        targets.append(n2)
                        seen.add(n2)
        fused = 0
        own = KeyFramePoints(kf)  # kf's points with their rows, re-gathered only where a merge changed them
        for t_id in targets:  # one short write phase per target
            with store.write():
                if store.has_keyframe(t_id):
                    fused += fuse_points(
                        store,
                        store.get_keyframe(t_id),
                        own.update(store),
                        cfg.fuse_search_radius_px,
                        max_distance=cfg.matcher.th_low,
                        chi2_gate=cfg.chi2.fuse_mono,
                        chi2_gate_stereo=cfg.chi2.stereo_rounded if cfg.fuse_right_coordinate_gate else None,
                    )
        with store.write():
            alive = [t for t in targets if store.has_keyframe(t)]
            if alive:
                ids = unique_point_ids([store.get_keyframe(t).point_ids for t in alive])
                fused += fuse_points(
                    store,
                    kf,
                    ids,
                    cfg.fuse_search_radius_px,
                    max_distance=cfg.matcher.th_low,
                    chi2_gate=cfg.chi2.fuse_mono,
                    chi2_gate_stereo=cfg.chi2.stereo_rounded if cfg.fuse_right_coordinate_gate else None,
                    refresh_survivors=False,  # the refresh below covers them (each holds a keypoint of kf)
                )
            # in the same write phase: nobody reads a merge's survivor before its descriptor is refreshed
            refresh_points(store, self._changed_points(kf).tolist())
            store.update_connections(kf.id)
        return fused

    def _changed_points(self, kf: KeyFrame) -> I64:
        """The points ``kf`` observes (ids (K,)) whose normal, depth range and descriptor a refresh could change since
        insertion refreshed them: those it did not refresh (triangulated, fused in, or a keyframe of a new map, which
        initialisation inserted) and those whose number of observations changed. Within one keyframe's step, until
        its local BA, the observations of a point in the map only grow (fusion adds observations of keyframes that
        do not observe the point, and a replacement adds to the survivor; removals come with local BA's outliers and
        keyframe culling, and loop correction parks local mapping between keyframes) and no position moves, so an
        unchanged count is an unchanged set of observations and the refresh would compute the values it holds."""
        ids = kf.point_ids[kf.point_ids >= 0]
        if self._inserted is None or self._inserted[0] != kf.id:
            return ids
        _, before, counts = self._inserted
        ids, now = _observation_counts(self.store, ids)
        at = np.minimum(np.searchsorted(before, ids), max(before.size - 1, 0))
        same = (before[at] == ids) & (counts[at] == now) if before.size else np.zeros(ids.size, bool)
        return ids[~same]

    # ---- VI-D (local BA) -----------------------------------------------------------------------------

    def _local_bundle_adjustment(self, kf: KeyFrame, abort: AbortToken | None) -> tuple[int, bool]:
        """Optimize the new keyframe, its covisible keyframes and all points they see; keyframes that see
        those points but are not covisible stay fixed (VI-D). The map's origin keyframe is always fixed."""
        store = self.store
        with store.read():
            local = [kf.id, *store.covisibility.neighbors(kf.id)]
            origin = store.origin_keyframe_id()
            free = [k for k in local if k != origin]
            # the local points (sorted ids) and their observations, by a mark per id and from the store's own
            # dictionaries (np.unique of ~30k ids sorted them; the points' read-only views were walked)
            pids = unique_point_ids([store.get_keyframe(k).point_ids for k in local])
            missing = ~store.has_points(pids)
            if missing.any():  # a keyframe's point_ids name only points of the map
                raise KeyError(f"local BA: map points {pids[missing][:5].tolist()} are not in the map")
            flat = gather_observations(store, pids)
            observers = unique_point_ids([flat[1]])  # the observing keyframes' ids, sorted
            fixed = np.setdiff1d(observers, np.array(free, np.int64)).tolist()
            if not fixed and free:
                fixed = [free.pop(free.index(min(free)))]
            if not free or not pids.size:
                return 0, False
            cfg = self.cfg
            snap = snapshot_bundle(
                store,
                free,
                fixed,
                pids,
                cfg.ba_iterations_first,
                cfg.ba_iterations_second,
                cfg.chi2.mono,
                cfg.chi2.stereo,
                flat=flat,
            )
        result = run_bundle(store, self.optimizer, snap, abort, self.cfg.ba_point_bad_max_observations)
        if self.cfg.ba_update_normal_and_depth:
            # ORB-SLAM2/3 LocalBundleAdjustment, "Recover optimized data" (aborted or not): every local point the BA
            # wrote gets UpdateNormalAndDepth, so tracking's viewing-angle filter (V-D), its predicted level and the
            # [d_min, d_max] range check see the optimised point and keyframes, not those at the point's creation
            with store.write():
                refresh_points(store, snap.point_ids.tolist(), normals=True, descriptors=False)
        return int(result.outlier.sum()), bool(result.aborted)

    # ---- VI-E -------------------------------------------------------------------------------------------

    def _cull_keyframes(self, kf: KeyFrame, abort: AbortToken | None = None) -> list[CulledKeyFrame]:
        """Erase covisible keyframes whose points are 90% seen by at least three other keyframes at the same
        or a finer scale (VI-E). The map's origin keyframe is never culled, nor a keyframe loop closing has pinned
        (ORB-SLAM SetNotErase). A point the culled keyframe leaves with at most ``point_bad_max_observations``
        observations is erased (ORB-SLAM2 KeyFrame::SetBadFlag -> MapPoint::EraseObservation: nObs <= 2 ->
        SetBadFlag).

        The covisible keyframes are visited best first; as ORB-SLAM3's KeyFrameCulling the visit stops after
        ``keyframe_culling_max_candidates`` of them, or ``keyframe_culling_max_candidates_aborted`` once ``abort``
        is set (mbAbortBA: a newer keyframe waits), every visited keyframe counted (0: no limit, ORB-SLAM2)."""
        cfg = self.cfg
        store = self.store
        origin = store.origin_keyframe_id()
        visit = store.covisibility.neighbors(kf.id)
        culled: list[CulledKeyFrame] = []
        if cfg.keyframe_culling_max_candidates > 0:
            visit = visit[: cfg.keyframe_culling_max_candidates]
        candidates = [k for k in visit if k != origin and store.has_keyframe(k)]
        if not candidates:
            return culled
        table = ObservationTable(store, candidates)
        slot = {k: c for c, k in enumerate(candidates)}
        pinned = self.pins.snapshot()
        aborted_limit = cfg.keyframe_culling_max_candidates_aborted
        # the counts of every candidate in one pass, taken again (for those after it) after each cull, which changes them
        counts: tuple[I64, I64] | None = None
        for count, k_id in enumerate(visit, start=1):
            if aborted_limit > 0 and count > aborted_limit and abort is not None and abort.is_set():
                break  # ORB-SLAM3: `count > 20 && mbAbortBA`, tested after the 21st keyframe, before the 22nd
            if k_id == origin or k_id in pinned or not store.has_keyframe(k_id):
                continue
            c = slot[k_id]
            if counts is None:
                counts = table.redundancies(candidates, cfg.keyframe_culling_min_observers, c)
            n_points, redundant = int(counts[0][c]), int(counts[1][c])
            if n_points and redundant > cfg.keyframe_culling_redundancy * n_points:
                k = store.get_keyframe(k_id)
                parent = store.spanning_tree.parent(k_id)
                T_kp = k.T_c_w @ invert_T(store.get_keyframe(parent).T_c_w) if parent is not None else np.eye(4)
                culled.append(CulledKeyFrame(k_id, parent, T_kp, k.T_c_w.copy()))
                seen = k.point_ids[k.point_ids >= 0].copy()
                store.remove_keyframe(k_id)
                seen = seen[store.has_points(seen)]
                erased = seen[:0]
                if seen.size:
                    erased = seen[store.point_rows(seen, "n_observations") <= cfg.point_bad_max_observations]
                    for pid in erased.tolist():
                        store.remove_point(pid)
                table.cull(k_id, erased)
                counts = None
                if self.place is not None:
                    self.place.remove(k_id)
        return culled


def _camera_free(kf: KeyFrame, camera: int) -> NDArray[np.bool_]:
    """(N,) bool: the keypoints triangulation may use in camera ``camera`` of ``kf``: all of a one-camera keyframe; of
    a two-camera one, that camera's keypoints whose stereo partner (if any) has no point."""
    feats = kf.features
    if not feats.two_cameras:
        return np.ones(len(feats), bool)
    out: NDArray[np.bool_] = feats.camera_index() == camera
    sm = feats.stereo_match
    if sm is not None:
        has = sm >= 0
        partner_point = np.zeros(len(feats), bool)
        partner_point[has] = np.asarray(kf.point_ids)[sm[has]] >= 0
        out &= ~partner_point
    return out


def _free_pairs(kf1: KeyFrame, kf2: KeyFrame, i1: I64, i2: I64) -> I64:
    """(S,) the rows of the candidate pairs (i1[m], i2[m]) (M,) that get a new point, in order: pair m is taken when
    neither feature (nor, in a two-camera keyframe, its stereo partner) observes a point or belongs to a pair taken
    before it (local mapping adds the pairs one after the other: a feature gets one point)."""
    free1 = np.asarray(kf1.point_ids)[i1] < 0
    free2 = np.asarray(kf2.point_ids)[i2] < 0
    rig = kf1.features.two_cameras or kf2.features.two_cameras
    if not rig and np.unique(i1).size == i1.size and np.unique(i2).size == i2.size:
        return np.flatnonzero(free1 & free2)  # distinct features: taking one pair frees or takes no other's feature
    taken1: set[int] = set()
    taken2: set[int] = set()
    keep: list[int] = []
    for m, (a, b) in enumerate(zip(i1.tolist(), i2.tolist(), strict=True)):
        if not (free1[m] and free2[m]) or a in taken1 or b in taken2:
            continue
        if rig and (_partner_taken(kf1, a, taken1) or _partner_taken(kf2, b, taken2)):
            continue
        taken1.add(a)
        taken2.add(b)
        keep.append(m)
    return np.array(keep, np.int64)


def _partner_taken(kf: KeyFrame, idx: int, taken: set[int]) -> bool:
    """Whether keypoint ``idx`` of a two-camera keyframe has a stereo partner observing a point or in ``taken`` (a
    pair taken before it: the point stands for both keypoints)."""
    sm = kf.features.stereo_match
    if sm is None or sm[idx] < 0:
        return False
    partner = int(sm[idx])
    return bool(kf.point_ids[partner] >= 0) or partner in taken


def _triangulate_with_depths(
    kf1: KeyFrame, kf2: KeyFrame, i1: I64, i2: I64, uv1: F64, uv2: F64, cos_par: F64, min_parallax_cos: float
) -> tuple[NDArray[np.bool_], F64]:
    """ORB-SLAM2 CreateNewMapPoints with stereo/RGB-D keyframes: a pair is triangulated from the two rays when their
    parallax beats the stereo parallax of its keypoints' depths (cos 2 atan(b / 2 / depth)) and is positive (any
    parallax with a depth on either side, above acos(min_parallax_cos) without); otherwise the keypoint whose
    depth gives the larger stereo parallax is back-projected at its depth. -> (ok (M,), xyz (M, 3) world)."""
    K1, K2 = kf1.camera.K, kf2.camera.K
    xyz = triangulate_points(kf1.T_c_w, kf2.T_c_w, K1, K2, uv1, uv2)
    d1 = kf1.features.depth_m[i1].astype(np.float64)
    d2 = kf2.features.depth_m[i2].astype(np.float64)
    st1 = np.isfinite(kf1.features.u_right_px[i1]) & np.isfinite(d1) & (d1 > 0)
    st2 = np.isfinite(kf2.features.u_right_px[i2]) & np.isfinite(d2) & (d2 > 0)
    b1 = kf1.features.bf / K1[0, 0]
    b2 = kf2.features.bf / K2[0, 0]
    none = cos_par + 1.0
    cps1 = np.where(st1, np.cos(2.0 * np.arctan2(b1 / 2.0, np.where(st1, d1, 1.0))), none)
    # ORB-SLAM2/3 CreateNewMapPoints: `if(bStereo1) cosParallaxStereo1 = ...; else if(bStereo2) cosParallaxStereo2 =
    # ...`: kf2's stereo parallax only when the new keyframe kf1 has no depth at the keypoint
    cps2 = np.where(st2 & ~st1, np.cos(2.0 * np.arctan2(b2 / 2.0, np.where(st2, d2, 1.0))), none)
    cps = np.minimum(cps1, cps2)
    rays = (cos_par < cps) & (cos_par > 0) & (st1 | st2 | (cos_par < min_parallax_cos))
    use1 = ~rays & st1 & (cps1 < cps2)
    use2 = ~rays & ~use1 & st2 & (cps2 < cps1)
    if use1.any():
        xyz[use1] = kf1.features.unproject_stereo(i1[use1], invert_T(kf1.T_c_w), K1)
    if use2.any():
        xyz[use2] = kf2.features.unproject_stereo(i2[use2], invert_T(kf2.T_c_w), K2)
    return rays | use1 | use2, xyz


def _level_sigma2(features: Features, idx: I64) -> F64:
    """``features.level_sigma2()[idx]`` (M,) px^2, computed for the M keypoints only (the same power per element)."""
    return np.power(features.scale_factor, 2.0 * features.level[idx].astype(np.float64))


def _level_scale(features: Features, idx: I64) -> F64:
    """``features.level_scale()[idx]`` (M,), computed for the M keypoints only (the same power per element)."""
    return np.power(features.scale_factor, features.level[idx].astype(np.float64))


def _pinhole_one_camera(kf: KeyFrame) -> bool:
    """Whether ``kf`` is a one-camera keyframe whose pipeline image is a pinhole camera's undistorted image (the
    compiled triangulation tests project with fx, fy, cx, cy)."""
    return not kf.features.two_cameras and isinstance(kf.camera, PinholeCamera) and kf.camera.image_undistorted


def _pinhole_intrinsics(kf: KeyFrame) -> F64:
    """(4,) fx, fy, cx, cy of a pinhole keyframe's camera."""
    cam = kf.camera
    assert isinstance(cam, PinholeCamera)
    return np.array([cam.fx, cam.fy, cam.cx, cam.cy], np.float64)


def _observation_counts(store: MapStore, point_ids: I64) -> tuple[I64, I64]:
    """The distinct ids among ``point_ids`` (-1: no point) of points in the map, sorted (K,), and each one's number
    of observing keyframes (K,)."""
    ids = np.unique(point_ids[point_ids >= 0])
    ids = ids[store.has_points(ids)]
    counts = np.fromiter((len(p.observations) for p in store.get_points(ids.tolist())), np.int64, count=ids.size)
    return ids, counts


def _median_depth(kf: KeyFrame, store: MapStore) -> float:
    """The median depth (m) in ``kf`` of the map points it observes (NaN: none)."""
    ids = kf.point_ids[kf.point_ids >= 0]
    ids = ids[store.has_points(ids)]
    if not ids.size:
        return float("nan")
    return _median(store.point_rows(ids, "xyz_w") @ kf.T_c_w[2, :3] + kf.T_c_w[2, 3])


def _median(values: F64) -> float:
    """``float(np.median(values))`` of a non-empty (n,) float64 array by one partition: the middle element, or the mean
    of the two middle ones as np.mean takes it ((a + b) / 2); NaN when any value is (np.median's partition and
    checks cost more than the depth test they feed, per neighbour)."""
    n = values.size
    k = n // 2
    # the last position too, as np.median: a NaN (sorted last) then lands there
    if n % 2:
        part = np.partition(values, (k, n - 1))
        middle = float(part[k])
    else:
        part = np.partition(values, (k - 1, k, n - 1))
        middle = float((part[k - 1] + part[k]) / 2.0)
    return float("nan") if np.isnan(part[-1]) else middle


def _pinhole_uv(kf: KeyFrame, idx: I64) -> F64:
    """(M, 2) px: keypoints ``idx`` of ``kf`` as undistorted pinhole pixels of its camera's K, where the epipolar
    search and the triangulation work: the pipeline image's own for a pinhole camera; for a two-camera keyframe with a
    Kannala-Brandt camera its bearings through K (K b / b_z; NaN for rays at or behind 90 degrees: left out), as
    ORB-SLAM3 triangulates fisheye keypoints from their unprojected rays (KannalaBrandt8::unprojectEig). A one-camera
    fisheye keyframe is refused as before."""
    if kf.camera.image_undistorted or not kf.features.two_cameras:
        require_pinhole_image(kf.camera, "local mapping (triangulation)")
        return kf.features.uv_undist_px[idx].astype(np.float64)
    b = kf.features.bearing[idx]
    K = kf.camera.K
    with np.errstate(invalid="ignore", divide="ignore"):
        n = np.where(b[:, 2:3] > 1e-6, b[:, :2] / b[:, 2:3], np.nan)
    out: F64 = n @ K[:2, :2].T + K[:2, 2]
    return out


def _epipole(kf1: KeyFrame, kf2: KeyFrame) -> F64:
    """(2,) px: the centre of ``kf1`` in the pipeline image of ``kf2``, ``project_points(kf2.T_c_w, kf1.center_w[None],
    kf2.camera)[0][0]``; for a PinholeCamera its ``project_image`` formula (u = fx x / z + cx, the same operations in
    the same order) on the one point, without the array round trips."""
    camera = kf2.camera
    if type(camera) is not PinholeCamera:
        return project_points(kf2.T_c_w, kf1.center_w[None], camera)[0][0]
    x, y, z = (kf1.center_w[None] @ kf2.T_c_w[:3, :3].T + kf2.T_c_w[:3, 3])[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.array([camera.fx * x / z + camera.cx, camera.fy * y / z + camera.cy], np.float64)


def _fundamental_21(kf1: KeyFrame, kf2: KeyFrame) -> F64:
    """F such that x2^T F x1 = 0 for undistorted pixels x1 in kf1 and x2 in kf2 (:func:`_pinhole_uv`)."""
    T21 = kf2.T_c_w @ invert_T(kf1.T_c_w)
    R21, t21 = T21[:3, :3], T21[:3, 3]
    E21 = hat(t21) @ R21
    return np.asarray(_inverse_K(kf2.camera).T @ E21 @ _inverse_K(kf1.camera))


#: K^-1 of the cameras seen so far (id -> (camera, K^-1)): np.linalg.inv per keyframe pair costs more than the epipolar
#: test it feeds; bounded, and an entry serves only the very camera object it was computed for
_INVERSE_K: dict[int, tuple[object, F64]] = {}


def _inverse_K(camera: Camera) -> F64:
    """(3, 3) np.linalg.inv(camera.K), computed once per camera object (the same numbers)."""
    entry = _INVERSE_K.get(id(camera))
    if entry is not None and entry[0] is camera:
        return entry[1]
    if len(_INVERSE_K) >= 64:
        _INVERSE_K.clear()
    inv = np.asarray(np.linalg.inv(camera.K), np.float64)
    inv.flags.writeable = False
    _INVERSE_K[id(camera)] = (camera, inv)
    return inv
