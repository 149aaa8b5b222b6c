"""ORB-SLAM sec. V-C: relocalization as ORB-SLAM2's Tracking::Relocalization: bag-of-words candidates -> BoW matches
(ratio 0.75, at least 15) -> EPnP in RANSAC per candidate (ORB-SLAM2's PnPsolver: minimal sets of 4, inliers by a
chi-square gate scaled by each keypoint's level, refined on the inliers), the candidates taken in turn a few
iterations each (round robin) -> motion-only BA -> guided search of the candidate's points (rotation check) ->
accepted with enough inliers. Every threshold is a ``pipeline.tracking.reloc_*`` value. The caller holds the map's
read lock."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from slamkit.interfaces import BowDescription, MapStore, PlaceRecognizer
from slamkit.map.entities import KeyFrame
from slamkit.pipeline.config import TrackingConfig
from slamkit.pipeline.frame import Frame
from slamkit.pipeline.map_points import predict_level
from slamkit.pipeline.projection import match_projected, project_points
from slamkit.pipeline.tracking.frame_pose import PoseRefiner

log = logging.getLogger("slamkit.tracking")

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass
class PnPRansac:
    """ORB-SLAM2's PnPsolver for one candidate: EPnP on random minimal sets in RANSAC, resumable (``iterate``).

    xyz_w: (N, 3) m world points; uv_px: (N, 2) px their keypoints in the frame's pinhole image (K); sigma2: (N,)
    px^2 the keypoints' level variances. The parameters are SetRansacParameters'(probability, minInliers,
    maxIterations, minSet, epsilon, th2): the inliers needed are max(min_inliers, epsilon N, min_set), and the
    iterations min(max_iterations, log(1 - p) / log(1 - eps^3)) with eps raised to (inliers needed) / N.
    """

    xyz_w: F64
    uv_px: F64
    sigma2: F64
    K: F64
    chi2: float
    probability: float
    min_inliers: int
    max_iterations: int
    min_set: int
    epsilon: float
    iterations_done: int = 0
    best_inliers: NDArray[np.bool_] | None = None
    best_T: F64 | None = None
    needed: int = field(init=False)
    iterations: int = field(init=False)

    def __post_init__(self) -> None:
        n = self.xyz_w.shape[0]
        self.needed = max(int(n * self.epsilon), self.min_inliers, self.min_set)
        eps = max(self.epsilon, self.needed / max(n, 1))
        # every correspondence must be an inlier: one hypothesis decides
        its = 1 if self.needed >= n else math.ceil(math.log(1 - self.probability) / math.log(1 - eps**3))
        self.iterations = max(1, min(its, self.max_iterations))

    def exhausted(self) -> bool:
        """All of its RANSAC iterations are spent (ORB-SLAM bNoMore), or it never had enough correspondences."""
        return self.iterations_done >= self.iterations or self.xyz_w.shape[0] < self.needed

    def _inliers(self, T: F64) -> NDArray[np.bool_]:
        xyz_c = self.xyz_w @ T[:3, :3].T + T[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = xyz_c[:, :2] / xyz_c[:, 2:3] @ self.K[:2, :2].T + self.K[:2, 2]
            err2 = np.sum((uv - self.uv_px) ** 2, axis=1)
        return np.asarray((err2 < self.sigma2 * self.chi2) & (xyz_c[:, 2] > 0))

    def _epnp(self, sel: I64) -> F64 | None:
        ok, rvec, tvec = cv2.solvePnP(self.xyz_w[sel], self.uv_px[sel], self.K, None, flags=cv2.SOLVEPNP_EPNP)
        if not ok or not np.all(np.isfinite(tvec)):
            return None
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(rvec)[0]
        T[:3, 3] = tvec.ravel()
        return T

    def iterate(self, n: int, rng: np.random.Generator) -> tuple[F64, NDArray[np.bool_]] | None:
        """Up to ``n`` more iterations. Returns (T_c_w (4, 4), (N,) inlier mask) as soon as a hypothesis with enough
        inliers refines (EPnP on its inliers) to more than the inliers needed; when the iterations run out, the
        best hypothesis with enough inliers; else None."""
        if self.exhausted():
            return None
        size = self.xyz_w.shape[0]
        for _ in range(n):
            if self.iterations_done >= self.iterations:
                break
            self.iterations_done += 1
            T = self._epnp(rng.choice(size, self.min_set, replace=False))
            if T is None:
                continue
            inl = self._inliers(T)
            count = int(inl.sum())
            if count < self.needed:
                continue
            if self.best_inliers is None or count > int(self.best_inliers.sum()):
                self.best_inliers, self.best_T = inl, T
            refined = self._epnp(np.flatnonzero(self.best_inliers))
            if refined is not None:
                r_inl = self._inliers(refined)
                if int(r_inl.sum()) > self.needed:
                    return refined, r_inl
        if self.iterations_done >= self.iterations and self.best_T is not None and self.best_inliers is not None:
            return self.best_T, self.best_inliers
        return None


@dataclass
class _Candidate:
    kf: KeyFrame
    pairs: I64  # (M, 2) keyframe feature, frame feature
    solver: PnPRansac


def relocalize(
    frame: Frame,
    bow: BowDescription,
    store: MapStore,
    place: PlaceRecognizer,
    cfg: TrackingConfig,
    refiner: PoseRefiner,
    best_neighbors: Callable[[int, int], list[int]],
    rng: np.random.Generator,
) -> int | None:
    """ORB-SLAM2 Relocalization. Every candidate of the place recognizer with at least ``reloc_min_bow_matches`` BoW
    matches gets a PnP RANSAC; in rounds, each candidate not yet exhausted runs ``reloc_pnp_iterations_per_turn``
    iterations; a pose it returns is optimized (at least ``reloc_min_pnp_inliers`` inliers), completed by a guided
    search of the candidate's points (radius ``reloc_search_radius_px``, ``reloc_search_max_distance`` bits, rotation
    check) when under ``min_local_map_inliers_after_reloc`` inliers, optimized again, and searched once more (3 px,
    64 bits) only when the inliers are then between ``reloc_fine_search_min_inliers`` and that; the first candidate
    reaching ``min_local_map_inliers_after_reloc`` inliers wins. Returns its id (frame.T_c_w and frame.point_ids
    set), or None (frame.T_c_w None, no matches).

    store: the active map; only its keyframes are tried. best_neighbors(kf_id, n): a candidate's covisibility
    neighbours in its own map (the Atlas's ``best_neighbors``), which group the candidates; candidates of other
    maps are skipped (ORB-SLAM3 DetectRelocalizationCandidates). rng: draws the RANSAC minimal sets."""
    matcher = cfg.matcher
    candidates: list[_Candidate] = []
    for kf_id, _ in place.relocalization_candidates(bow, best_neighbors):
        if not store.has_keyframe(kf_id):
            continue
        kf = store.get_keyframe(kf_id)
        if kf.bow is None:
            continue
        valid = store.has_points(kf.point_ids)
        pairs = place.match(
            kf.features,
            kf.bow,
            frame.features,
            bow,
            matcher.ratio_relocalization,
            valid,
            None,
            max_distance=matcher.th_low,
            rotation_bins=matcher.rotation_bins,
        )
        if frame.features.two_cameras:
            # a two-camera frame: EPnP on camera 1's matches (its keypoints and K); camera 2's join in the motion-only
            # BA of the verification (ORB-SLAM3 Relocalization builds its MLPnPsolver on the frame's camera-1 rays)
            pairs = pairs[pairs[:, 1] < frame.features.n_left]
        if pairs.shape[0] < cfg.reloc_min_bow_matches:
            continue
        uv = frame.features.uv_undist_px[pairs[:, 1]].astype(np.float64)
        if not frame.camera.image_undistorted:
            # a fisheye keypoint enters EPnP as its bearing seen through K (ORB-SLAM3 solves PnP on bearings);
            # rays at or behind 90 degrees have no such pixel and are left out
            b = frame.features.bearing[pairs[:, 1]]
            ahead = b[:, 2] > 0
            pairs, b = pairs[ahead], b[ahead]
            if pairs.shape[0] < cfg.reloc_min_bow_matches:
                continue
            uv = (b[:, :2] / b[:, 2:3]) @ frame.camera.K[:2, :2].T + frame.camera.K[:2, 2]
        xyz = store.point_rows(kf.point_ids[pairs[:, 0]], "xyz_w")
        sigma2 = frame.features.level_sigma2()[pairs[:, 1]]
        solver = PnPRansac(
            np.ascontiguousarray(xyz, np.float64),
            np.ascontiguousarray(uv, np.float64),
            sigma2,
            np.asarray(frame.camera.K, np.float64),
            cfg.chi2.mono,
            cfg.reloc_pnp_ransac_confidence,
            cfg.reloc_min_pnp_inliers,
            cfg.reloc_pnp_ransac_iterations,
            cfg.reloc_pnp_min_set,
            cfg.reloc_pnp_epsilon,
        )
        candidates.append(_Candidate(kf, pairs, solver))
    active = [c for c in candidates if not c.solver.exhausted()]
    while active:
        for cand in active:
            found = cand.solver.iterate(cfg.reloc_pnp_iterations_per_turn, rng)
            if found is None:
                continue
            if _verify(frame, cand, found[0], found[1], store, cfg, refiner):
                log.info("relocalized frame %d against keyframe %d", frame.index, cand.kf.id)
                return cand.kf.id
        active = [c for c in active if not c.solver.exhausted()]
    frame.point_ids[:] = -1
    frame.T_c_w = None
    return None


def _verify(
    frame: Frame,
    cand: _Candidate,
    T: F64,
    inliers: NDArray[np.bool_],
    store: MapStore,
    cfg: TrackingConfig,
    refiner: PoseRefiner,
) -> bool:
    """ORB-SLAM2 Relocalization after a PnP pose: motion-only BA, then the guided searches; True when the frame ends
    with ``min_local_map_inliers_after_reloc`` inliers (frame.T_c_w and frame.point_ids hold the result)."""
    needed = cfg.min_local_map_inliers_after_reloc
    kf = cand.kf
    frame.point_ids[:] = -1
    sel = cand.pairs[inliers]
    frame.point_ids[sel[:, 1]] = kf.point_ids[sel[:, 0]]
    refiner.optimize(frame, T)
    good = refiner.discard_outliers(frame)
    if good < cfg.reloc_min_pnp_inliers:
        return False
    if good < needed:
        added = search_keyframe_points(
            frame, kf, store, cfg.reloc_search_radius_px, cfg.reloc_search_max_distance, cfg.matcher.rotation_bins
        )
        if good + added >= needed:
            assert frame.T_c_w is not None
            refiner.optimize(frame, frame.T_c_w)
            good = refiner.optimize(frame, frame.T_c_w)
            # only when close: the camera is already well optimized with many points (ORB-SLAM2: 30 < nGood < 50)
            if cfg.reloc_fine_search_min_inliers < good < needed:
                added = search_keyframe_points(
                    frame,
                    kf,
                    store,
                    cfg.reloc_search_radius_fine_px,
                    cfg.reloc_search_max_distance_fine,
                    cfg.matcher.rotation_bins,
                )
                if good + added >= needed:
                    assert frame.T_c_w is not None
                    refiner.optimize(frame, frame.T_c_w)
                    good = refiner.optimize(frame, frame.T_c_w)
    if good < needed:
        return False
    refiner.discard_outliers(frame)
    return True


def search_keyframe_points(
    frame: Frame, kf: KeyFrame, store: MapStore, radius_px: float, max_distance: int, rotation_bins: int
) -> int:
    """ORB-SLAM SearchByProjection(Frame, KeyFrame, sAlreadyFound, th, ORBdist) with its orientation check (the
    relocalization's ORBmatcher(0.9, true)): project the keyframe's points not matched yet with the frame's pose and
    match them around the projection (radius_px x scale of the predicted level, Hamming <= max_distance bits); the
    distance must lie in the point's scale-invariance range (ORB-SLAM's 0.8 d_min, 1.2 d_max); the keypoint angle
    differences must fall in the fullest bins of a ``rotation_bins`` histogram. Returns the matches added to
    frame.point_ids."""
    assert frame.T_c_w is not None
    found = frame.point_ids[frame.point_ids >= 0]
    kf_feat = np.flatnonzero(kf.point_ids >= 0)
    kf_ids = kf.point_ids[kf_feat]
    keep = ~np.isin(kf_ids, found) & store.has_points(kf_ids)
    pids = kf_ids[keep]
    angles = kf.features.angle_deg[kf_feat[keep]].astype(np.float64)
    if pids.size == 0:
        return 0
    feats = frame.features
    xyz = store.point_rows(pids, "xyz_w")
    uv, _, valid = project_points(frame.T_c_w, xyz, frame.camera)
    center = -frame.T_c_w[:3, :3].T @ frame.T_c_w[:3, 3]
    dist = np.linalg.norm(xyz - center, axis=1)
    d_min = store.point_rows(pids, "d_min_m")
    d_max = store.point_rows(pids, "d_max_m")
    ok = valid & (dist >= 0.8 * d_min) & (dist <= 1.2 * d_max)
    ok &= frame.bounds.contains(np.nan_to_num(uv, nan=-1e9))
    q = np.flatnonzero(ok)
    if q.size == 0:
        return 0
    level = predict_level(d_max[q], dist[q], feats.scale_factor, feats.n_levels)
    taken = frame.point_ids >= 0
    if feats.two_cameras:
        taken |= feats.camera_index() != 0  # camera 1's keypoints only: the points are projected through camera 1
    m = match_projected(
        feats,
        taken,
        frame.bounds,
        uv[q],
        store.point_rows(pids[q], "descriptor"),
        radius_px * np.power(feats.scale_factor, level),
        level - 1,
        level + 1,
        max_distance,
        None,
        angles[q],
        rotation_bins,
    )
    frame.point_ids[m.feature] = pids[q[m.query]]
    return len(m)
