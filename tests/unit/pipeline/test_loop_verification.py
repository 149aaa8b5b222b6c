"""Geometric verification of loop hypotheses (ORB-SLAM3 sec. VI) on a small synthetic map. Place A (the loop's
side) is a textured wall; place B, 12 m away and facing the other way, is its perfect twin (identical points
and descriptors, as in the ``twins`` scene where the repeated wall fills 95 % of the view). A true revisit of A
agrees; B agrees in every keyframe too, and only the ~180 degree turn its correction implies rejects it."""

from __future__ import annotations

import numpy as np
import pytest
from omegaconf import OmegaConf

from slamkit.config import compose_config
from slamkit.features import Features, Observations
from slamkit.geometry.camera import PinholeCamera
from slamkit.geometry.se3 import invert_T
from slamkit.geometry.sim3 import Sim3
from slamkit.geometry.so3 import so3_exp
from slamkit.map.atlas import Atlas
from slamkit.map.entities import KeyFrame, MapPoint
from slamkit.map.store import InMemoryMapStore
from slamkit.optim.factory import build_optimizer
from slamkit.pipeline.config import PipelineConfig
from slamkit.pipeline.loop_closing import LoopCloser
from slamkit.pipeline.loop_verification import (
    PendingLoop,
    VerificationThresholds,
    advance_pending,
    check_covisibles,
    check_keyframe,
    loop_rotation_deg,
    loop_window,
    project_window,
)
from slamkit.pipeline.map_points import update_normal_and_depth
from slamkit.plugins import ComponentRegistry

CAMERA = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)


def _record(features: Features) -> Observations:
    """The monocular observation record of hand-made features (bearings through CAMERA)."""
    return Observations.monocular(features, CAMERA.unproject_image(features.uv_undist_px.astype(np.float64)))


# ORB-SLAM3's defaults (conf/pipeline/orbslam.yaml): radius 3 px, 30 matches.
TH = VerificationThresholds(3.0, 30, 50)
N_WALL, N_OTHER = 60, 240
# place B = G place A: turned by 180 degrees about the vertical through (6, 2, 0) (12 m from A's cameras)
TWIN = np.array([[-1.0, 0.0, 0.0, 12.0], [0.0, -1.0, 0.0, 4.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


def pose_at(x: float, y: float = 0.0) -> np.ndarray:
    """T_c_w of a camera at (x, y, 0) looking along +y (world z up, camera y down)."""
    T_w_c = np.eye(4)
    T_w_c[:3, :3] = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    T_w_c[:3, 3] = [x, y, 0.0]
    return invert_T(T_w_c)


def translation(t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = t
    return T


class World:
    """Points of place A on the plane y = 4 m: the twin wall (x < -0.2) and other surfaces (x > 0.2)."""

    def __init__(self, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        wall = np.column_stack([rng.uniform(-1.6, -0.2, N_WALL), np.full(N_WALL, 4.0), rng.uniform(-1, 1, N_WALL)])
        other = np.column_stack([rng.uniform(0.2, 1.6, N_OTHER), np.full(N_OTHER, 4.0), rng.uniform(-1, 1, N_OTHER)])
        self.xyz_a = np.vstack([wall, other])
        desc_wall = rng.integers(0, 256, (N_WALL, 32), dtype=np.uint8)
        self.desc_a = np.vstack([desc_wall, rng.integers(0, 256, (N_OTHER, 32), dtype=np.uint8)])
        self.store = InMemoryMapStore()
        # the loop's side: three keyframes at place A, the map's world is the true one
        self.loop_ids = self.add_group([pose_at(x) for x in (0.0, 0.2, -0.2)], self.xyz_a, self.desc_a, np.eye(4))

    def add_group(
        self, T_c_w_true: list[np.ndarray], xyz_true: np.ndarray, desc: np.ndarray, drift: np.ndarray
    ) -> list[int]:
        """Keyframes seeing ``xyz_true`` with ``desc`` from the true poses, stored in a map whose world is
        ``drift`` @ true world (poses T_c_w_true @ drift^-1, points drift @ xyz), with their own map points."""
        store = self.store
        xyz_map = xyz_true @ drift[:3, :3].T + drift[:3, 3]
        pids = [store.new_point_id() for _ in range(len(xyz_true))]
        kf_ids: list[int] = []
        for T in T_c_w_true:
            xyz_c = xyz_true @ T[:3, :3].T + T[:3, 3]
            uv = (xyz_c[:, :2] / xyz_c[:, 2:]) * 500.0 + np.array([320.0, 240.0])
            n = len(uv)
            feats = _record(
                Features(
                    uv.astype(np.float32),
                    uv.astype(np.float32),
                    np.zeros(n, np.int32),
                    np.zeros(n, np.float32),
                    np.ones(n, np.float32),
                    desc.copy(),
                    1.2,
                    8,
                )
            )
            kf = KeyFrame(store.new_keyframe_id(), len(kf_ids), 0.0, T @ invert_T(drift), CAMERA, feats, np.full(n, -1))
            store.add_keyframe(kf)
            kf_ids.append(kf.id)
        for i, pid in enumerate(pids):
            store.add_point(MapPoint(pid, xyz_map[i].copy(), desc[i].copy(), kf_ids[0], kf_ids[0]))
            for k in kf_ids:
                store.add_observation(pid, k, i)
        keyframes = {k: store.get_keyframe(k) for k in kf_ids}
        for pid in pids:
            update_normal_and_depth(store, store.get_point(pid), keyframes)
        for k in kf_ids:
            store.update_connections(k)
        return kf_ids


@pytest.fixture
def world() -> World:
    return World()


def test_the_window_is_the_loop_keyframe_and_its_covisible_points(world: World) -> None:
    window = loop_window(world.store, world.loop_ids[0])
    assert window == list(range(N_WALL + N_OTHER))


def test_a_true_revisit_agrees_in_the_keyframe_and_its_covisibles(world: World) -> None:
    # The revisit's map drifted by 0.7 m; the hypothesis S_c_w is the true pose (what the Sim3 recovers).
    drift = translation(np.array([0.5, -0.4, 0.3]))
    ids = world.add_group([pose_at(x, 0.3) for x in (0.05, 0.15, -0.1, 0.25)], world.xyz_a, world.desc_a, drift)
    window = loop_window(world.store, world.loop_ids[0])
    current = world.store.get_keyframe(ids[0])
    S_cw = Sim3.from_se3(pose_at(0.05, 0.3))
    check, proj = check_keyframe(world.store, current, S_cw, window, TH)
    assert check.agrees and check.visible == N_WALL + N_OTHER and check.ratio > 0.95
    # every match pairs a feature with the loop point it observes (feature i sees point i of place A)
    assert all(pid == feat for feat, pid in proj.matches.items())
    covis = check_covisibles(world.store, current, S_cw, window, TH, n_covisibles=5, needed=3)
    assert [c.agrees for c in covis] == [True, True, True]
    assert {c.kf_id for c in covis} <= set(ids[1:])


def twin_group(world: World, xs: tuple[float, ...]) -> list[int]:
    """Keyframes at place B seeing B = G A from T_c_w = T_c_w(A) G^-1, in an undrifted map."""
    return world.add_group(
        [pose_at(x) @ invert_T(TWIN) for x in xs], world.xyz_a @ TWIN[:3, :3].T + TWIN[:3, 3], world.desc_a, np.eye(4)
    )


def test_a_perfect_twin_agrees_everywhere_but_implies_a_half_turn(world: World) -> None:
    ids = twin_group(world, (0.05, 0.15, -0.1, 0.25))
    window = loop_window(world.store, world.loop_ids[0])
    current = world.store.get_keyframe(ids[0])
    # The aliasing hypothesis: the current camera placed at A, where it would see exactly this view.
    S_cw = Sim3.from_se3(pose_at(0.05))
    check, _ = check_keyframe(world.store, current, S_cw, window, TH)
    assert check.agrees and check.matches == check.visible == N_WALL + N_OTHER
    covis = check_covisibles(world.store, current, S_cw, window, TH, n_covisibles=5, needed=3)
    assert [c.agrees for c in covis] == [True, True, True]
    # what rejects it: the map would have to turn by 180 degrees
    assert loop_rotation_deg(current.T_c_w, S_cw) == pytest.approx(180.0, abs=1e-6)


def test_the_rotation_of_a_drift_correction_is_its_angle() -> None:
    T_c_w = pose_at(0.3, 0.2)
    turn = Sim3(1.3, so3_exp(np.array([0.0, 0.0, np.radians(7.0)])), np.array([0.5, -1.0, 0.2]))
    # the loop side's frame is the map's turned by 7 degrees (and scaled, moved): S_c_w = T_c_w S_w_w'
    assert loop_rotation_deg(T_c_w, Sim3.from_se3(T_c_w) @ turn) == pytest.approx(7.0, abs=1e-9)
    assert loop_rotation_deg(T_c_w, Sim3.from_se3(T_c_w)) == pytest.approx(0.0, abs=1e-6)


def test_the_loop_closer_rejects_the_twin_with_its_reason(world: World) -> None:
    ids = twin_group(world, (0.05, 0.15, -0.1, 0.25))
    closer = loop_closer(world)
    window = loop_window(world.store, world.loop_ids[0])
    info: dict[str, object] = {}
    current = world.store.get_keyframe(ids[0])
    verdict = closer._verify(current, world.loop_ids[0], Sim3.from_se3(pose_at(0.05)), window, {}, info)
    assert verdict is None and closer._pending is None
    assert info["correction_rotation_deg"] == pytest.approx(180.0)
    assert str(info["rejected"]).startswith("verification: the loop would turn the map by 180.0 deg > 20.0 deg")


def test_the_loop_closer_accepts_a_revisit_its_covisibles_confirm(world: World) -> None:
    drift = translation(np.array([0.5, -0.4, 0.3]))
    ids = world.add_group([pose_at(x, 0.3) for x in (0.05, 0.15, -0.1, 0.25)], world.xyz_a, world.desc_a, drift)
    closer = loop_closer(world)
    window = loop_window(world.store, world.loop_ids[0])
    info: dict[str, object] = {}
    S_cw = Sim3.from_se3(pose_at(0.05, 0.3))
    verdict = closer._verify(world.store.get_keyframe(ids[0]), world.loop_ids[0], S_cw, window, {0: 0}, info)
    assert verdict is not None and verdict.loop_kf_id == world.loop_ids[0] and verdict.S_cw is S_cw
    assert info["agreeing"] == 3 and "rejected" not in info
    assert info["correction_rotation_deg"] == pytest.approx(0.0, abs=1e-6)


def test_a_wrong_hypothesis_finds_too_few_matches(world: World) -> None:
    ids = world.add_group([pose_at(x) for x in (0.05, 0.15)], world.xyz_a, world.desc_a, np.eye(4))
    window = loop_window(world.store, world.loop_ids[0])
    S_cw = Sim3.from_se3(pose_at(0.35))  # 30 cm off: 37 px at 4 m, beyond the 3 px window
    check, _ = check_keyframe(world.store, world.store.get_keyframe(ids[0]), S_cw, window, TH)
    assert not check.agrees and check.matches < TH.min_matches and "matches <" in check.why


def test_points_outside_their_scale_range_are_not_predicted_visible(world: World) -> None:
    ids = world.add_group([pose_at(0.0, -3.0)], world.xyz_a, world.desc_a, np.eye(4))  # 7 m away: beyond 1.2 d_max
    window = loop_window(world.store, world.loop_ids[0])
    proj = project_window(
        world.store, world.store.get_keyframe(ids[0]), Sim3.from_se3(pose_at(0.0, -3.0)), window, 3.0, 50
    )
    assert proj.visible == 0 and proj.matches == {} and proj.ratio == 0.0


def test_a_pending_loop_is_accepted_after_three_agreeing_keyframes(world: World) -> None:
    drift = translation(np.array([0.5, -0.4, 0.3]))
    xs = (0.05, 0.1, 0.15, 0.2)
    ids = world.add_group([pose_at(x, 0.3) for x in xs], world.xyz_a, world.desc_a, drift)
    window = loop_window(world.store, world.loop_ids[0])
    first = world.store.get_keyframe(ids[0])
    pending = PendingLoop(
        world.loop_ids[0], first.id, first.T_c_w.copy(), Sim3.from_se3(pose_at(xs[0], 0.3)), window, 1
    )
    states = [advance_pending(world.store, pending, world.store.get_keyframe(k), TH, 3, 2) for k in ids[1:3]]
    assert [s.state for s in states] == ["agreed", "accepted"]
    assert pending.coincidences == 3 and pending.last_kf_id == ids[2]
    # the hypothesis carried by the tracked motion is the third keyframe's true pose (drift undone)
    assert np.allclose(states[-1].S_k_w.to_se3(), pose_at(xs[2], 0.3), atol=1e-9)
    assert len(states[-1].matches) > 0.95 * (N_WALL + N_OTHER)


def test_a_pending_loop_is_dropped_after_two_misses(world: World) -> None:
    ids = world.add_group([pose_at(x) for x in (0.05, 0.1, 0.15)], world.xyz_a, world.desc_a, np.eye(4))
    window = loop_window(world.store, world.loop_ids[0])
    first = world.store.get_keyframe(ids[0])
    # a hypothesis 40 cm off: the next keyframes do not find the window where it predicts it
    pending = PendingLoop(world.loop_ids[0], first.id, first.T_c_w.copy(), Sim3.from_se3(pose_at(0.45)), window, 1)
    states = [advance_pending(world.store, pending, world.store.get_keyframe(k), TH, 3, 2).state for k in ids[1:]]
    assert states == ["missed", "dropped"]
    assert pending.coincidences == 1 and pending.misses == 2


def loop_closer(world: World) -> LoopCloser:
    """A LoopCloser over the world's map with the default config, optimizer and place recognizer."""
    cfg = compose_config()
    registry = ComponentRegistry.discover()
    pipeline = PipelineConfig.from_node(OmegaConf.to_container(cfg.pipeline, resolve=True))  # type: ignore[arg-type]
    place = registry.instantiate("place", cfg.place)
    for k in world.store.keyframe_ids():
        kf = world.store.get_keyframe(k)
        world.store.set_keyframe_bow(k, place.transform(kf.features.descriptors))
    optimizer = build_optimizer(cfg.optimizer, registry)
    return LoopCloser(pipeline.loop_closing, Atlas.of(world.store), optimizer, place, np.random.default_rng(0))


def test_the_loop_closer_records_a_pending_loop_and_closes_it_on_the_third_agreeing_keyframe(world: World) -> None:
    drift = translation(np.array([0.5, -0.4, 0.3]))
    xs = (0.05, 0.1, 0.15, 0.2)
    ids = world.add_group([pose_at(x, 0.3) for x in xs], world.xyz_a, world.desc_a, drift)
    closer = loop_closer(world)
    first = world.store.get_keyframe(ids[0])
    window = loop_window(world.store, world.loop_ids[0])
    # as _verify leaves it when one covisible keyframe agreed with the first keyframe's hypothesis
    closer._pending = PendingLoop(
        world.loop_ids[0], first.id, first.T_c_w.copy(), Sim3.from_se3(pose_at(xs[0], 0.3)), window, 1
    )
    second = closer.step(world.store.get_keyframe(ids[1]))
    assert second.pending is not None and second.pending["state"] == "agreed" and second.loop_kf_id is None
    assert second.pending["coincidences"] == 2 and "confirmed" in second.reason
    third = closer.step(world.store.get_keyframe(ids[2]))
    assert third.pending is not None and third.pending["state"] == "accepted"
    assert third.loop_kf_id == world.loop_ids[0] and third.matches > 0.95 * (N_WALL + N_OTHER)
    # the correction moved the drifted keyframe back to its true pose
    assert np.allclose(world.store.get_keyframe(ids[2]).T_c_w, pose_at(xs[2], 0.3), atol=1e-6)
    # detection pinned the keyframes it used against culling; the correction released them
    assert closer.pins.total_pinned >= 3 and not closer.pins.snapshot()


@pytest.mark.parametrize(
    ("key", "default"),
    [
        ("verify_covisible_keyframes", 5),  # ORB-SLAM3 nNumCovisibles
        ("verify_coincidences", 3),  # ORB-SLAM3 mnLoopNumCoincidences >= 3
        ("verify_search_radius_px", 3.0),  # ORB-SLAM3 FindMatchesByProjection th = 3
        ("verify_min_matches", 30),  # ORB-SLAM3 nProjMatches = 30
        ("verify_max_misses", 2),  # ORB-SLAM3 mnLoopNumNotFound >= 2
        ("max_loop_rotation_deg", 20.0),  # ORB-SLAM3 "BAD LOOP": 0.349 rad
    ],
)
def test_verification_constants_default_to_the_papers_and_are_configurable(key: str, default: float) -> None:
    typed = PipelineConfig.from_node(OmegaConf.to_container(compose_config().pipeline))  # type: ignore[arg-type]
    assert getattr(typed.loop_closing, key) == default
    new = default * 2
    cfg = compose_config([f"pipeline.loop_closing.{key}={new}"])
    typed = PipelineConfig.from_node(OmegaConf.to_container(cfg.pipeline))  # type: ignore[arg-type]
    assert getattr(typed.loop_closing, key) == new


# ---- ORB-SLAM3 DetectCommonRegionsFromBoW (LoopCloser._common_region) ------------------------------------


def test_a_true_revisit_is_a_common_region_with_the_drift_undone(world: World) -> None:
    """The revisit's own map drifted by 0.7 m: pooled BoW matches, Sim3 RANSAC, guided matching, Sim3
    optimisation and refined matching recover the current keyframe's true pose and match all the window."""
    drift = translation(np.array([0.5, -0.4, 0.3]))
    ids = world.add_group([pose_at(x, 0.3) for x in (0.05, 0.15, -0.1, 0.25)], world.xyz_a, world.desc_a, drift)
    closer = loop_closer(world)
    info: dict[str, object] = {}
    hyp = closer._common_region(world.store.get_keyframe(ids[0]), world.loop_ids[0], info)
    assert hyp is not None, info
    assert hyp.matched_kf_id in world.loop_ids and "rejected" not in info
    assert np.allclose(hyp.S_cw.to_se3(), pose_at(0.05, 0.3), atol=1e-3)
    assert len(hyp.matches) >= 0.95 * (N_WALL + N_OTHER)
    assert all(pid == feat for feat, pid in hyp.matches.items())  # feature i sees point i of place A


def test_a_translated_twin_with_other_surroundings_is_rejected_by_geometry(world: World) -> None:
    """Place C shows A's wall 12 m further along x (same orientation: no rotation prior can tell) with other
    surroundings. Its wall alone matches (BoW, the Sim3, the first guided search), but the refined guided search
    over the candidate's window finds too few points (ORB-SLAM3 nProjOptMatches = 80)."""
    shift = translation(np.array([12.0, 0.0, 0.0]))
    rng = np.random.default_rng(5)
    other = np.column_stack([rng.uniform(0.2, 1.6, N_OTHER), np.full(N_OTHER, 4.0), rng.uniform(-1, 1, N_OTHER)])
    xyz_c = np.vstack([world.xyz_a[:N_WALL], other]) + np.array([12.0, 0.0, 0.0])
    desc_c = np.vstack([world.desc_a[:N_WALL], rng.integers(0, 256, (N_OTHER, 32), dtype=np.uint8)])
    ids = world.add_group([pose_at(x) @ invert_T(shift) for x in (0.05, 0.15, -0.1, 0.25)], xyz_c, desc_c, np.eye(4))
    closer = loop_closer(world)
    info: dict[str, object] = {}
    hyp = closer._common_region(world.store.get_keyframe(ids[0]), world.loop_ids[0], info)
    assert hyp is None
    assert int(info["bow_matches"]) >= 20  # type: ignore[call-overload]  # the twin wall fools the BoW stage
    assert "matches <" in str(info["rejected"])


def test_a_candidate_whose_group_is_connected_to_the_current_keyframe_is_aborted(world: World) -> None:
    """ORB-SLAM3 bAbortByNearKF: a keyframe of the candidate's covisible group is connected to the current
    keyframe (here the candidate's own neighbour is the current keyframe), so its matches would confirm the
    current side against itself."""
    store = world.store
    current, cand = world.loop_ids[2], world.loop_ids[0]
    assert current in store.covisibility.neighbors(cand)
    closer = loop_closer(world)
    info: dict[str, object] = {}
    assert closer._common_region(store.get_keyframe(current), cand, info) is None
    assert "connected to the current keyframe" in str(info["rejected"])
    assert "bow_matches" not in info  # aborted before any matching


# ---- ORB-SLAM3 sec. III-A: merge detection (a common region in another map of the Atlas) -----------------------


def two_map_closer(world: World, drift: np.ndarray, n_keyframes: int = 12) -> tuple[LoopCloser, Atlas, list[int]]:
    """The world's map (place A) kept as map 0 of an Atlas; an active map 1 whose world is ``drift`` @ the true
    world holds ``n_keyframes`` keyframes revisiting place A (more than ORB-SLAM3's 12-keyframe minimum before any
    detection). Every keyframe of map 0 is in the keyframe database, as a run leaves them."""
    atlas = Atlas(lambda ids: InMemoryMapStore(ids=ids), None, first=world.store)
    closer = loop_closer(world)
    closer.atlas = atlas
    for k in world.store.keyframe_ids():
        bow = world.store.get_keyframe(k).bow
        assert bow is not None
        closer.place.add(k, bow)
    assert atlas.create_map() == 1
    world.store = atlas.active
    xs = np.linspace(-0.2, 0.3, n_keyframes)
    ids = world.add_group([pose_at(float(x), 0.3) for x in xs], world.xyz_a, world.desc_a, drift)
    for k in ids:
        kf = atlas.active.get_keyframe(k)
        atlas.active.set_keyframe_bow(k, closer.place.transform(kf.features.descriptors))
    return closer, atlas, ids


def test_a_revisit_of_another_maps_place_is_a_merge_with_the_maps_relative_pose(world: World) -> None:
    """The active map's world is turned by 90 degrees and moved from map 0's (two maps' frames are unrelated: no
    rotation bound applies): the merge candidates come from map 0 only, the common region is found there and three
    covisible keyframes of the active map agree, so the merge is accepted with S_cw the current keyframe's true pose
    in map 0's world; loop detection in the active map finds nothing."""
    drift = np.eye(4)
    drift[:3, :3] = so3_exp(np.array([0.0, 0.0, np.radians(90.0)]))
    drift[:3, 3] = [3.0, -1.0, 0.5]
    closer, atlas, ids = two_map_closer(world, drift)
    current = atlas.active.get_keyframe(ids[-1])
    detection = closer.detect(current)
    out = detection.outcome
    assert out.merge_candidates and {atlas.map_of(k) for k in out.merge_candidates} == {0}
    merge = detection.merge
    assert merge is not None, out.merge_tried
    assert merge.map_id == 0 and merge.merge_kf_id in world.loop_ids
    assert out.merge_kf_id == merge.merge_kf_id and out.merge_map_id == 0 and out.merge_matches == len(merge.matches)
    assert np.allclose(merge.S_cw.to_se3(), pose_at(0.3, 0.3), atol=1e-3)
    assert abs(merge.S_cw.s - 1.0) < 1e-3
    assert len(merge.matches) >= 0.95 * (N_WALL + N_OTHER)
    tried = out.merge_tried[[t["candidate"] for t in out.merge_tried].index(merge.merge_kf_id)]
    assert tried["map"] == 0 and tried["agreeing"] == 3
    assert detection.loop is None and out.loop_kf_id is None


def test_no_merge_is_searched_in_an_active_map_of_too_few_keyframes(world: World) -> None:
    """ORB-SLAM3 NewDetectCommonRegions: no common region is searched while the active map is small."""
    closer, atlas, ids = two_map_closer(world, translation(np.array([1.0, 0.0, 0.0])), n_keyframes=10)
    detection = closer.detect(atlas.active.get_keyframe(ids[-1]))
    assert detection.merge is None and detection.outcome.merge_candidates == []


def test_a_merge_a_single_covisible_confirms_waits_for_the_next_keyframes(world: World) -> None:
    """One agreeing covisible keyframe keeps the merge pending (ORB-SLAM3 mnMergeNumCoincidences); the next
    keyframes of the active map confirm it with the tracked motion, and the third agreeing keyframe accepts it."""
    closer, atlas, ids = two_map_closer(world, translation(np.array([0.5, -0.4, 0.3])))
    store = atlas.active
    first = store.get_keyframe(ids[0])
    window = loop_window(atlas.get(0), world.loop_ids[0])
    closer._pending_merge = (
        0,
        PendingLoop(world.loop_ids[0], first.id, first.T_c_w.copy(), Sim3.from_se3(pose_at(-0.2, 0.3)), window, 1),
    )
    second = closer.detect(store.get_keyframe(ids[1]))
    assert second.merge is None
    assert second.outcome.merge_pending is not None and second.outcome.merge_pending["state"] == "agreed"
    third = closer.detect(store.get_keyframe(ids[2]))
    assert third.outcome.merge_pending is not None and third.outcome.merge_pending["state"] == "accepted"
    assert third.merge is not None and third.merge.map_id == 0 and closer._pending_merge is None
    xs = np.linspace(-0.2, 0.3, 12)
    assert np.allclose(third.merge.S_cw.to_se3(), pose_at(float(xs[2]), 0.3), atol=1e-6)


# ---- ORB-SLAM3 sec. III-B: map merging (LoopCloser.merge, slamkit/pipeline/map_merging.py) ---------------------


def test_a_merge_welds_the_active_map_into_the_matched_maps_frame_and_scale(world: World) -> None:
    """The active map revisits map 0's place in its own frame (turned, moved) and scale (half map 0's): the merge
    moves it into map 0's frame and scale, takes map 0's keyframes and points in, fuses the duplicates (the revisit's
    points are map 0's points), and leaves one map in the Atlas, the active one, with one spanning tree."""
    drift = np.eye(4)
    drift[:3, :3] = so3_exp(np.array([0.0, np.radians(30.0), np.radians(60.0)]))
    drift[:3, 3] = [2.0, 1.0, -0.5]
    closer, atlas, ids = two_map_closer(world, drift)
    from slamkit.pipeline.map_merging import transform_map

    with atlas.active.write():
        transform_map(atlas.active, Sim3(0.5, np.eye(3), np.zeros(3)))  # the active map's scale: half map 0's
    merges = []
    closer.on_merge = merges.append
    map0_kfs, map0_points = atlas.get(0).keyframe_ids(), atlas.get(0).point_ids()
    out = closer.step(atlas.active.get_keyframe(ids[-1]))
    assert out.merge_map_id == 0 and out.merge_transform is not None
    assert atlas.map_ids() == [1] and atlas.active_id == 1
    store = atlas.active
    assert set(map0_kfs) | set(ids) == set(store.keyframe_ids())
    assert [m.merged_map_id for m in merges] == [0] and merges[0].moved_kf_ids == frozenset(ids)
    assert merges[0].G.s == pytest.approx(2.0, rel=1e-3)
    # every keyframe of the merged map at its true pose (map 0's world is the true one), the revisit's scale undone
    xs = np.linspace(-0.2, 0.3, 12)
    for k, x in zip(ids, xs, strict=True):
        assert np.allclose(store.get_keyframe(k).T_c_w, pose_at(float(x), 0.3), atol=1e-3), k
    for k in map0_kfs:
        assert np.allclose(store.get_keyframe(k).T_c_w, atlas.get(1).get_keyframe(k).T_c_w)
    # duplicates fused: the revisit's features observe map 0's points, no point of the revisit's is left
    assert store.point_ids() == map0_points
    current = store.get_keyframe(ids[-1])
    assert (np.sort(current.point_ids[current.point_ids >= 0]) == np.array(map0_points)).all()
    for pid in map0_points:
        assert np.allclose(store.get_point(pid).xyz_w, world.xyz_a[pid], atol=1e-6)
    # one spanning tree over every keyframe: one root, no cycle
    tree = store.spanning_tree
    roots = [k for k in store.keyframe_ids() if tree.parent(k) is None]
    assert len(roots) == 1
    for k in store.keyframe_ids():
        seen, j = set(), k
        while tree.parent(j) is not None:
            assert j not in seen
            seen.add(j)
            j = tree.parent(j)  # type: ignore[assignment]
    assert (min(ids[-1], out.merge_kf_id), max(ids[-1], out.merge_kf_id)) in store.loop_edges()  # type: ignore[type-var]
    assert not closer.pins.snapshot()  # the merge released the keyframe detection pinned


@pytest.mark.parametrize(("global_ba_stopped", "global_bas"), [(False, 0), (True, 1)])
def test_a_merge_runs_a_global_ba_only_in_place_of_one_it_stopped(
    world: World, global_ba_stopped: bool, global_bas: int
) -> None:
    """ORB-SLAM3 MergeLocal (bRelaunchBA): a visual merge launches no global BA of its own; a global BA of an earlier
    loop that was running when the merge began (stopped for it) runs again, on the merged map. The two maps meet in
    the welding area only: a global BA after it moved their relative scale (docs/BENCHMARKS.md, "The threaded
    long-loop kidnap within its bar")."""
    drift = np.eye(4)
    drift[:3, :3] = so3_exp(np.array([0.0, 0.0, np.radians(40.0)]))
    drift[:3, 3] = [1.0, -0.5, 0.2]
    closer, atlas, ids = two_map_closer(world, drift)
    assert closer.cfg.global_ba and not closer.cfg.merge_global_ba  # the defaults
    detection = closer.detect(atlas.active.get_keyframe(ids[-1]))
    assert detection.merge is not None
    closer.merge(detection, global_ba_stopped=global_ba_stopped)
    assert atlas.map_ids() == [1]
    assert [g.loop_kf_id for g in closer.global_bas] == [ids[-1]] * global_bas
    assert not any(g.aborted for g in closer.global_bas)
