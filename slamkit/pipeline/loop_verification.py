"""Geometric verification of a loop hypothesis (ORB-SLAM3, Campos et al. T-RO 2021, sec. VI "Place
recognition", LoopClosing::DetectCommonRegionsFromBoW / DetectCommonRegionsFromLastKF /
DetectAndReffineSim3FromLastKF).

A loop hypothesis is a Sim3 ``S_c_w`` putting the current keyframe in the frame of the loop keyframe's side of
the map. Its evidence is re-checked where more than one view can contradict it: the points of the loop's
*local window* (the loop keyframe and its covisible keyframes) are projected with the hypothesis into

* the current keyframe's best covisible keyframes (``S_j_w = T_j_c S_c_w``): three that agree accept the loop
  at once;
* otherwise the next keyframes (``S_k_w = T_k_l S_l_w``, l the last keyframe that agreed): the hypothesis is
  kept pending and accepted after three agreeing keyframes in all, dropped after two consecutive misses.

A keyframe agrees when enough of the window's points are matched there (ORB-SLAM3's counts).

Appearance and local geometry cannot tell a place from its perfect twin (the synthetic ``twins`` scene: the
same wall fills 95 % of both views, the corridor is symmetric): every keyframe agrees with the false
hypothesis. What gives it away is the correction it implies: the map would have to turn by ~180 degrees,
far more than visual odometry drifts over a loop. ORB-SLAM3 (LoopClosing::Run) rejects a loop whose
correction turns an inertial map by more than 0.349 rad about gravity ("BAD LOOP"); ``loop_rotation_deg``
applies that bound to the whole rotation, as a drift prior for visual maps too.

Unlike ORB-SLAM3's DetectAndReffineSim3FromLastKF, a pending hypothesis is not re-optimized in each new
keyframe: it is carried by the tracked motion (a few keyframes, little drift) and judged by the same tight
projection test; the accepting keyframe's matches are the ones the loop fusion uses.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from slamkit.geometry.sim3 import Sim3
from slamkit.interfaces import MapStore
from slamkit.map.entities import KeyFrame
from slamkit.pipeline.frame import ImageBounds
from slamkit.pipeline.projection import frustum_test, match_projected

I64 = NDArray[np.int64]

#: ORB-SLAM V-D / SearchByProjection: a point seen at more than 60 degrees from its mean viewing direction is
#: not searched.
_MIN_VIEW_COS = 0.5


@dataclass(frozen=True)
class VerificationThresholds:
    """What one keyframe must show to agree with a loop hypothesis (see ``LoopClosingConfig``).

    search_radius_px: window radius at pyramid level 0 (scaled by the predicted level's scale).
    min_matches: matched window points.
    max_distance: Hamming threshold of a match, bits (pipeline.matcher.th_low).
    """

    search_radius_px: float
    min_matches: int
    max_distance: int


def loop_rotation_deg(T_c_w: NDArray[np.float64], S_c_w: Sim3) -> float:
    """Rotation, degrees, of the correction a loop hypothesis implies for the keyframe's map: the keyframe
    at T_c_w (map frame) is said to be at S_c_w (the loop side's frame), so the map's frame turns by the
    rotation of S_w_w' = T_w_c S_c_w (ORB-SLAM3 LoopClosing::Run, g2oSww_new)."""
    R = T_c_w[:3, :3].T @ S_c_w.R
    cos = (np.trace(R) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


@dataclass(frozen=True)
class WindowProjection:
    """The loop window projected into one keyframe with a hypothesis.

    visible: window points predicted visible there (in the image, positive depth, within the scale-invariance
    distances, seen at less than 60 degrees from their mean viewing direction). matches: feature index of that
    keyframe -> matched window point id.
    """

    visible: int
    matches: dict[int, int]

    @property
    def ratio(self) -> float:
        """Matched over predicted visible (0 when nothing is predicted visible)."""
        return len(self.matches) / self.visible if self.visible else 0.0


@dataclass
class KeyframeCheck:
    """One keyframe's verdict on a loop hypothesis (recorded in loops.json)."""

    kf_id: int
    visible: int
    matches: int
    ratio: float
    agrees: bool
    why: str = ""

    def as_dict(self) -> dict[str, object]:
        return {
            "kf": self.kf_id,
            "visible": self.visible,
            "matches": self.matches,
            "ratio": round(self.ratio, 3),
            "agrees": self.agrees,
            **({"why": self.why} if self.why else {}),
        }


@dataclass
class PendingLoop:
    """A loop hypothesis waiting for more keyframes to agree (ORB-SLAM3 mnLoopNumCoincidences > 0).

    S_l_w: the hypothesis for the last keyframe that agreed (``last_kf_id``, whose pose then was ``T_l_w``).
    window: the loop window's point ids. coincidences: keyframes that agreed so far; misses: consecutive
    keyframes that did not.
    """

    loop_kf_id: int
    last_kf_id: int
    T_l_w: NDArray[np.float64]
    S_l_w: Sim3
    window: list[int]
    coincidences: int
    misses: int = 0
    matches: dict[int, int] = field(default_factory=dict)

    def predict(self, store: MapStore, kf: KeyFrame) -> Sim3:
        """The hypothesis carried to ``kf`` by the relative motion tracked since the last agreeing keyframe:
        S_k_w = T_k_l S_l_w, with T_k_l from the current poses (the last keyframe's pose when it agreed, if it
        has been culled since)."""
        T_l_w = store.get_keyframe(self.last_kf_id).T_c_w if store.has_keyframe(self.last_kf_id) else self.T_l_w
        T_k_l = kf.T_c_w @ np.linalg.inv(T_l_w)
        return Sim3.from_se3(T_k_l) @ self.S_l_w


def loop_window(store: MapStore, loop_kf_id: int) -> list[int]:
    """Ids of the points seen by the loop keyframe and its covisible keyframes (ORB-SLAM's loop map points),
    sorted."""
    group = (
        [loop_kf_id, *store.covisibility.neighbors(loop_kf_id)] if loop_kf_id in store.covisibility else [loop_kf_id]
    )
    return sorted(
        {
            int(p)
            for k in group
            if store.has_keyframe(k)
            for p in store.get_keyframe(k).point_ids
            if p >= 0 and store.has_point(int(p))
        }
    )


def common_region_keyframes(store: MapStore, kf_id: int, n_covisibles: int) -> list[int]:
    """A keyframe and its ``n_covisibles`` best covisible keyframes (ORB-SLAM3 DetectCommonRegionsFromBoW:
    the candidate's group whose BoW matches are pooled, and the group whose points are projected)."""
    return [kf_id, *store.covisibility.best_neighbors(kf_id, n_covisibles)] if kf_id in store.covisibility else [kf_id]


def points_of(store: MapStore, kf_ids: list[int]) -> list[int]:
    """Ids of the live points the keyframes ``kf_ids`` see, each once, in keyframe then feature order."""
    seen: set[int] = set()
    out: list[int] = []
    for k in kf_ids:
        if not store.has_keyframe(k):
            continue
        for p in store.get_keyframe(k).point_ids:
            q = int(p)
            if q >= 0 and q not in seen and store.has_point(q):
                seen.add(q)
                out.append(q)
    return out


def verification_window(store: MapStore, matched_kf_id: int, n_covisibles: int, current_kf_id: int) -> list[int]:
    """ORB-SLAM3 FindMatchesByProjection's window: the matched keyframe, its ``n_covisibles`` best covisibles and,
    for each of those, up to ``n_covisibles`` of their best covisibles not connected to the current keyframe
    (the current keyframe's side must not confirm a hypothesis against itself). Point ids, sorted."""
    cov = store.covisibility
    first = common_region_keyframes(store, matched_kf_id, n_covisibles)
    current_side = {current_kf_id, *cov.neighbors(current_kf_id)} if current_kf_id in cov else {current_kf_id}
    group = [k for k in first if k not in current_side]
    chosen = set(group)
    for k in first[1:]:
        added = 0
        for j in cov.best_neighbors(k, n_covisibles) if k in cov else []:
            if added >= n_covisibles:
                break
            if j not in chosen and j not in current_side:
                chosen.add(j)
                group.append(j)
                added += 1
    return sorted(points_of(store, group))


def project_window(
    store: MapStore,
    kf: KeyFrame,
    S_k_w: Sim3,
    window: list[int],
    radius_px: float,
    max_distance: int,
    taken: NDArray[np.bool_] | None = None,
) -> WindowProjection:
    """ORB-SLAM SearchByProjection(Scw): project the window's points into ``kf`` with the hypothesis S_k_w,
    keep those predicted visible, search each in a radius of ``radius_px`` x the scale of its predicted level
    among features of that level or the one below, best Hamming distance <= max_distance (ORB-SLAM: TH_LOW), each
    feature once. For a two-camera keyframe the points are projected into camera 1 through its own model and matched
    among camera 1's keypoints only (ORB-SLAM3: pKF->mpCamera->project and GetFeaturesInArea of the left grid).

    window: point ids; taken: (F,) bool, features of ``kf`` not to match (None: all free).
    """
    pids = [p for p in window if store.has_point(p)]
    if not pids:
        return WindowProjection(0, {})
    points = [store.get_point(p) for p in pids]
    feats = kf.features
    bounds = ImageBounds.of(kf.camera)
    # The SE3 [R, t/s] of a Sim3 pose projects like it and has the camera centre in the loop side's frame,
    # where the window's points and their scale-invariance distances live.
    test = frustum_test(
        S_k_w.to_se3(),
        kf.camera,
        bounds,
        np.stack([p.xyz_w for p in points]),
        np.stack([p.normal_w for p in points]),
        np.array([p.d_min_m for p in points]),
        np.array([p.d_max_m for p in points]),
        _MIN_VIEW_COS,
        feats.scale_factor,
        feats.n_levels,
    )
    vis = np.flatnonzero(test.visible)
    if vis.size == 0:
        return WindowProjection(0, {})
    level = test.predicted_level[vis]
    blocked = np.zeros(len(feats), bool) if taken is None else taken
    if feats.two_cameras:
        blocked = blocked | (feats.camera_index() != 0)
    m = match_projected(
        feats,
        blocked,
        bounds,
        test.uv_px[vis],
        np.stack([points[i].descriptor for i in vis]),
        radius_px * feats.scale_factor ** level.astype(np.float64),
        np.maximum(level - 1, 0),
        level,
        max_distance,
        None,
        None,
        None,
    )
    return WindowProjection(int(vis.size), {int(f): pids[int(vis[q])] for q, f in zip(m.query, m.feature, strict=True)})


def check_keyframe(
    store: MapStore, kf: KeyFrame, S_k_w: Sim3, window: list[int], th: VerificationThresholds
) -> tuple[KeyframeCheck, WindowProjection]:
    """Does ``kf`` agree with the hypothesis S_k_w? Enough window points matched (ORB-SLAM3
    DetectCommonRegionsFromLastKF). The share of the predicted visible points matched is recorded only."""
    proj = project_window(store, kf, S_k_w, window, th.search_radius_px, th.max_distance)
    n = len(proj.matches)
    why = f"{n} matches < {th.min_matches}" if n < th.min_matches else ""
    return KeyframeCheck(kf.id, proj.visible, n, proj.ratio, not why, why), proj


def check_covisibles(
    store: MapStore,
    kf: KeyFrame,
    S_c_w: Sim3,
    window: list[int],
    th: VerificationThresholds,
    n_covisibles: int,
    needed: int,
    window_store: MapStore | None = None,
) -> list[KeyframeCheck]:
    """ORB-SLAM3's check of a new hypothesis with the current keyframe's best ``n_covisibles`` covisible
    keyframes, each with S_j_w = T_j_c S_c_w; stops once ``needed`` agree. ``store`` holds ``kf`` and its covisible
    keyframes, ``window_store`` the window's points (None: ``store``; another map of the Atlas for a merge)."""
    T_w_c = np.linalg.inv(kf.T_c_w)
    checks: list[KeyframeCheck] = []
    neighbors = store.covisibility.best_neighbors(kf.id, n_covisibles) if kf.id in store.covisibility else []
    for j in neighbors:
        if sum(c.agrees for c in checks) >= needed:
            break
        if not store.has_keyframe(j):
            continue
        kf_j = store.get_keyframe(j)
        S_j_w = Sim3.from_se3(kf_j.T_c_w @ T_w_c) @ S_c_w
        checks.append(check_keyframe(store if window_store is None else window_store, kf_j, S_j_w, window, th)[0])
    return checks


@dataclass(frozen=True)
class PendingStep:
    """What a new keyframe did to a pending loop: ``state`` is "agreed" (one more coincidence), "accepted"
    (enough coincidences: close the loop with ``S_k_w`` and ``matches``), "missed" or "dropped" (too many
    consecutive misses)."""

    state: str
    check: KeyframeCheck
    S_k_w: Sim3
    matches: dict[int, int]


def advance_pending(
    store: MapStore,
    pending: PendingLoop,
    kf: KeyFrame,
    th: VerificationThresholds,
    coincidences_needed: int,
    max_misses: int,
    refine: Callable[[KeyFrame, Sim3, WindowProjection], str] | None = None,
    window_store: MapStore | None = None,
) -> PendingStep:
    """ORB-SLAM3's confirmation of a pending loop by the next keyframe (NewDetectCommonRegions with
    mnLoopNumCoincidences > 0): carry the hypothesis to ``kf`` with the tracked motion and check it there.
    refine: ORB-SLAM3 DetectAndReffineSim3FromLastKF's further checks on a keyframe that passed the projection
    (the Sim3 re-optimised, more matches), returning why it fails ("" = it agrees); None: the projection only.
    ``store`` holds ``kf`` and the last agreeing keyframe, ``window_store`` the window's points (None: ``store``;
    another map of the Atlas for a pending merge). Updates ``pending`` in place (coincidences, misses, last agreeing
    keyframe)."""
    S_k_w = pending.predict(store, kf)
    check, proj = check_keyframe(store if window_store is None else window_store, kf, S_k_w, pending.window, th)
    if check.agrees and refine is not None:
        why = refine(kf, S_k_w, proj)
        if why:
            check.agrees, check.why = False, why
    if check.agrees:
        pending.coincidences += 1
        pending.misses = 0
        pending.last_kf_id, pending.T_l_w, pending.S_l_w = kf.id, kf.T_c_w.copy(), S_k_w
        pending.matches = proj.matches
        state = "accepted" if pending.coincidences >= coincidences_needed else "agreed"
        return PendingStep(state, check, S_k_w, proj.matches)
    pending.misses += 1
    return PendingStep("dropped" if pending.misses >= max_misses else "missed", check, S_k_w, {})
