"""A small hand-built Atlas of two maps with every kind of map state, for the map-file tests (tests/unit/map)."""

from __future__ import annotations

from typing import Any

import numpy as np
from slamkit_dbow.recognizer import DbowPlaceRecognizer

from slamkit.features import Features, Observations
from slamkit.geometry.camera import KannalaBrandtCamera, PinholeCamera
from slamkit.interfaces import MapStore
from slamkit.map.atlas import Atlas
from slamkit.map.entities import KeyFrame, MapPoint
from slamkit.map.ids import IdAllocator
from slamkit.map.store import InMemoryMapStore
from slamkit.sensors import FrameRecords

CAMERA = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0, dist=(0.01, -0.002, 0.0, 0.0, 0.0))
FISHEYE = KannalaBrandtCamera(640, 480, 300.0, 300.0, 320.0, 240.0, k=(0.01, 0.0, 0.0, 0.0))
#: a rig's second camera (another calibration than FISHEYE's)
FISHEYE_2 = KannalaBrandtCamera(640, 480, 302.0, 301.0, 318.0, 242.0, k=(0.012, -0.001, 0.0, 0.0))
N_FEATS = 80


def new_store(ids: IdAllocator) -> MapStore:
    return InMemoryMapStore(ids=ids)


def rig_observations(rng: np.random.Generator, camera: Any) -> Observations:
    """A non-rectified rig's two-camera record (frontend=stereo_rig): N_FEATS / 2 keypoints per camera, every third
    camera-1 keypoint stereo-matched to a camera-2 one (both ways) with its triangulated point."""
    obs = observations(rng, camera, stereo=False)
    n_left = N_FEATS // 2
    match = np.full(N_FEATS, -1, np.int64)
    left = np.arange(0, n_left, 3)
    right = n_left + rng.permutation(N_FEATS - n_left)[: left.size]
    match[left], match[right] = right, left
    xyz = np.full((N_FEATS, 3), np.nan)
    xyz[left] = xyz[right] = rng.uniform([-1, -1, 1], [1, 1, 5], (left.size, 3))
    depth = np.full(N_FEATS, np.nan, np.float32)
    depth[left] = xyz[left, 2]
    T_c2_c1 = np.eye(4)
    T_c2_c1[:3, :3] = np.array([[np.cos(0.26), 0.0, -np.sin(0.26)], [0.0, 1.0, 0.0], [np.sin(0.26), 0.0, np.cos(0.26)]])
    T_c2_c1[0, 3] = -0.11
    return Observations(
        **{name: getattr(obs, name) for name in Features.__dataclass_fields__},
        bearing=obs.bearing,
        u_right_px=np.full(N_FEATS, np.nan, np.float32),
        depth_m=depth,
        bf=0.11 * 300.0,
        th_depth_m=0.11 * 40.0,
        sensor="stereo",
        n_left=n_left,
        stereo_match=match,
        xyz_c1=xyz,
        camera_2=FISHEYE_2,
        T_c2_c1=T_c2_c1,
    )


def observations(rng: np.random.Generator, camera: Any, stereo: bool | str) -> Observations:
    """stereo: False (monocular), True (RGB-D-like) or "rig" (a non-rectified rig's two cameras)."""
    if stereo == "rig":
        return rig_observations(rng, camera)
    uv = rng.uniform(0, 480, (N_FEATS, 2)).astype(np.float32)
    feats = Features(
        uv,
        (uv + 0.25).astype(np.float32),
        rng.integers(0, 8, N_FEATS).astype(np.int32),
        rng.uniform(0, 360, N_FEATS).astype(np.float32),
        rng.uniform(0, 1, N_FEATS).astype(np.float32),
        rng.integers(0, 256, (N_FEATS, 32), dtype=np.uint8),
        1.2,
        8,
    )
    obs = Observations.monocular(feats, camera.unproject_image(feats.uv_undist_px.astype(np.float64)))
    if not stereo:
        return obs
    depth = rng.uniform(1, 5, N_FEATS).astype(np.float32)
    depth[::7] = np.nan
    return Observations(
        **{name: getattr(obs, name) for name in Features.__dataclass_fields__},
        bearing=obs.bearing,
        u_right_px=(uv[:, 0] - 40.0 / depth).astype(np.float32),
        depth_m=depth,
        bf=40.0,
        th_depth_m=3.2,
        sensor="rgbd",
    )


def fill_map(atlas: Atlas, rng: np.random.Generator, n_kfs: int, camera: Any, stereo: bool | str = False) -> None:
    """Keyframes along x with bags of words, points seen by 2-4 of them, graphs, counters, a loop edge, a culled
    keyframe and culled points: every part of a map's state."""
    store, place = atlas.active, atlas.place
    assert place is not None
    kf_ids: list[int] = []
    free: dict[int, int] = {}
    for i in range(n_kfs):
        kf_id = store.new_keyframe_id()
        T = np.eye(4)
        T[0, 3] = -0.1 * i
        feats = observations(rng, camera, stereo)
        store.add_keyframe(KeyFrame(kf_id, 3 * i, 0.1 * i, T, camera, feats, np.full(N_FEATS, -1, np.int64)))
        bow = place.transform(feats.descriptors)
        store.set_keyframe_bow(kf_id, bow)
        place.add(kf_id, bow)
        kf_ids.append(kf_id)
        free[kf_id] = 0
        if i == 0:
            continue
        for j in range(25):  # points seen by this keyframe and up to 3 before it (as local mapping makes them)
            observers = kf_ids[max(0, i - int(rng.integers(1, 4))) :]
            pid = store.new_point_id()
            point = MapPoint(
                pid,
                rng.uniform([-1, -1, 3], [1, 1, 6]),
                rng.integers(0, 256, 32).astype(np.uint8),
                observers[0],
                observers[0],
                rng.normal(size=3),
                0.5 + j * 1e-3,
                7.0,
            )
            store.add_point(point)
            for k in observers:
                if free[k] < N_FEATS:
                    store.add_observation(pid, k, free[k])
                    free[k] += 1
        if i == 1:
            store.update_connections(kf_ids[0])
        store.update_connections(kf_id)
    pids = np.array(store.point_ids(), np.int64)
    store.increase_visible(pids[::2], 3)
    store.increase_found(pids[::3], 2)
    store.add_loop_edge(kf_ids[0], kf_ids[-1])
    store.remove_keyframe(kf_ids[2])
    place.remove(kf_ids[2])
    for pid in store.point_ids()[:5]:
        store.remove_point(pid)
    store.bump_epoch()


def _two_maps(place: DbowPlaceRecognizer, seed: int, n_first: int, stereo: bool | str) -> Atlas:
    """Map 0: ``n_first`` monocular pinhole keyframes; map 1 (active): 6 fisheye keyframes of kind ``stereo``."""
    place.database.clear()
    atlas = Atlas(new_store, place)
    rng = np.random.default_rng(seed)
    fill_map(atlas, rng, n_first, CAMERA)
    atlas.create_map()
    fill_map(atlas, rng, 6, FISHEYE, stereo=stereo)
    return atlas


def build_atlas(place: DbowPlaceRecognizer, seed: int = 0) -> Atlas:
    """Two maps: map 0 monocular pinhole, map 1 (active) RGB-D-like keyframes on a fisheye camera."""
    return _two_maps(place, seed, 8, True)


def build_rig_atlas(place: DbowPlaceRecognizer, seed: int = 0) -> Atlas:
    """Two maps: map 0 monocular pinhole, map 1 (active) a fisheye rig's two-camera keyframes."""
    return _two_maps(place, seed, 5, "rig")


def build_frames(atlas: Atlas, seed: int = 0, per_map: int = 12) -> dict[int, FrameRecords]:
    """map id -> ``per_map`` frames of a session (increasing timestamps, each relative to a keyframe of that map by a
    rigid pose): what a runner's ``map_frames()`` gives a map file."""
    rng = np.random.default_rng(seed)
    out: dict[int, FrameRecords] = {}
    for map_id, store in atlas.items():
        kf_ids = np.array(store.keyframe_ids(), np.int64)
        T = np.tile(np.eye(4), (per_map, 1, 1))
        for i in range(per_map):
            q = rng.normal(size=4)
            w, x, y, z = q / np.linalg.norm(q)
            T[i, :3, :3] = [
                [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
            ]
            T[i, :3, 3] = rng.normal(scale=0.2, size=3)
        out[map_id] = FrameRecords(
            np.cumsum(rng.uniform(0.01, 0.1, per_map)) + 10.0 * map_id,
            np.arange(per_map, dtype=np.int64),
            rng.choice(kf_ids, per_map),
            T,
        )
    return out


class RecordingPlace(DbowPlaceRecognizer):
    """A keyframe database that counts what is added to it (nothing may be, when a load fails)."""

    def __init__(self) -> None:
        super().__init__()
        self.added = 0

    def add(self, keyframe_id: int, bow: Any) -> None:
        self.added += 1
        super().add(keyframe_id, bow)
