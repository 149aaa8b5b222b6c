"""Map entities: plain data owned by a MapStore (ORB-SLAM sec. III-C).

Ids come from the store's allocator (slamkit/map/ids.py); nothing here counts or locks. Algorithm-specific
scratch state lives in the algorithms, not on these objects.

Entities are read-only to everyone but their store, and Python enforces it: the dataclasses are frozen, their
arrays are not writeable (``kf.point_ids[i] = -1`` or ``point.xyz_w[0] = 0.0`` raise ValueError) and a point's
observations are a read-only mapping. Every change goes through a MapStore method; a store changes its own
entities with the helpers at the end of this module (``replace_fields``, ``frozen_view``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import numpy as np
from numpy.typing import DTypeLike, NDArray

from slamkit.features import Observations
from slamkit.interfaces import BowDescription, Camera

F64 = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class KeyFrame:
    """A keyframe (ORB-SLAM III-C).

    T_c_w: (4, 4) pose, world -> camera (read-only). features: the observation record of every keypoint of the
    image (slamkit.features.Observations: pixel, point in the pipeline's image, bearing, right coordinate, depth).
    point_ids: (N,) int64 (read-only), the map point observed by each feature, -1 for none; before the keyframe is
    in a map, the points tracking matched (the store keeps those still in the map as its observations when it adds
    the keyframe). bow: the bag of words of the features, once a place recognizer has described it.
    """

    id: int
    frame_index: int
    timestamp_s: float
    T_c_w: F64
    camera: Camera
    features: Observations
    point_ids: NDArray[np.int64]
    bow: BowDescription | None = None

    def __post_init__(self) -> None:
        replace_fields(self, T_c_w=frozen_copy(self.T_c_w, np.float64), point_ids=frozen_copy(self.point_ids, np.int64))

    def __setstate__(self, state: dict[str, Any]) -> None:  # copies (pickle, deepcopy) are read-only too
        replace_fields(self, **state)
        self.__post_init__()

    @property
    def T_w_c(self) -> F64:
        """(4, 4) camera -> world."""
        R, t = self.T_c_w[:3, :3], self.T_c_w[:3, 3]
        out = np.eye(4)
        out[:3, :3] = R.T
        out[:3, 3] = -R.T @ t
        return out

    @property
    def center_w(self) -> F64:
        """(3,) m, the camera centre in the world frame (a new array each call).

        Computed once per pose: kept with the pose array it came from and recomputed when ``T_c_w`` is another array
        (a pose is replaced, never written in place: it is read-only); local mapping reads each keyframe's centre
        many times per step (triangulation's baselines, epipoles and parallax, the points' refreshes)."""
        T = self.T_c_w
        cached = self.__dict__.get("_center_w")
        if cached is None or cached[0] is not T:
            R, t = T[:3, :3], T[:3, 3]
            cached = (T, np.asarray(-R.T @ t))
            self.__dict__["_center_w"] = cached
        return np.array(cached[1])

    def n_tracked_points(self) -> int:
        return int(np.count_nonzero(self.point_ids >= 0))


@dataclass(frozen=True, eq=False, init=False)
class MapPoint:
    """A 3D point of the map (ORB-SLAM III-C).

    xyz_w: (3,) m, position in the world. normal_w: (3,) unit mean viewing direction (from the cameras
    observing it towards the point). descriptor: (32,) uint8, the observation descriptor with the least median
    Hamming distance to the others. d_min_m / d_max_m: the distances within which ORB's scale invariance lets
    it be observed. observations: keyframe id -> feature index in that keyframe (read-only; empty until the store
    records observations). ref_kf_id: the keyframe that d_min/d_max refer to. first_kf_id: the keyframe that
    created it. The visible/found counters of VI-B live in the store (``MapStore.point_rows(ids, "n_visible")``).
    """

    id: int
    xyz_w: F64
    descriptor: NDArray[np.uint8]
    ref_kf_id: int
    first_kf_id: int
    normal_w: F64
    d_min_m: float
    d_max_m: float
    observations: Mapping[int, int]

    def __init__(
        self,
        id: int,
        xyz_w: F64,
        descriptor: NDArray[np.uint8],
        ref_kf_id: int,
        first_kf_id: int,
        normal_w: F64 | None = None,
        d_min_m: float = 0.0,
        d_max_m: float = float("inf"),
        observations: Mapping[int, int] | None = None,
    ) -> None:
        # written straight into __dict__ (one call, read-only copies of the arrays): local mapping makes hundreds
        # of points per keyframe, and a frozen dataclass's generated __init__ costs several times more
        self.__dict__.update(
            id=id,
            xyz_w=frozen_copy(xyz_w, np.float64),
            descriptor=frozen_copy(descriptor, np.uint8),
            ref_kf_id=ref_kf_id,
            first_kf_id=first_kf_id,
            normal_w=_ZERO3 if normal_w is None else frozen_copy(normal_w, np.float64),
            d_min_m=float(d_min_m),
            d_max_m=float(d_max_m),
            observations=_NO_OBSERVATIONS if not observations else MappingProxyType(dict(observations)),
        )

    def __getstate__(self) -> dict[str, Any]:
        """A copy (pickle, deepcopy) belongs to no store: it takes the observations as they are now."""
        return {**self.__dict__, "observations": dict(self.observations)}

    def __setstate__(self, state: dict[str, Any]) -> None:
        MapPoint.__init__(self, **state)


def observation_weight(features: Observations, feature_index: int) -> int:
    """ORB-SLAM's weight of one keyframe observation in MapPoint::Observations(): 2 for a stereo / RGB-D keypoint
    with a right coordinate (ORB-SLAM2 AddObservation: ``nObs += 2`` when mvuRight[idx] >= 0); 2 for a camera-1
    keypoint of a two-camera record with a stereo match, whose camera-2 partner observes the point too (ORB-SLAM3
    AddObservation adds 1 for each of the tuple's left and right indices; slamkit records the camera-1 index and reads
    the partner from ``Observations.stereo_match``); else 1."""
    if features.n_left >= 0:
        sm = features.stereo_match
        return 2 if sm is not None and feature_index < features.n_left and sm[feature_index] >= 0 else 1
    return 2 if np.isfinite(features.u_right_px[feature_index]) else 1


# ---- for MapStore implementations only: how a store changes the entities it owns -------------------------------


def frozen_copy(array: Any, dtype: DTypeLike) -> NDArray[Any]:
    """A read-only copy of ``array`` as ``dtype``."""
    out = np.array(array, dtype=dtype, copy=True)
    out.setflags(write=False)
    return out


def frozen_view(array: NDArray[Any]) -> NDArray[Any]:
    """A read-only view of ``array``: the store keeps ``array`` and writes to it, holders of the view see the
    change but cannot write."""
    view = array.view()
    view.setflags(write=False)
    return view


def replace_fields(entity: KeyFrame | MapPoint, **values: object) -> None:
    """Set fields of a frozen entity in place (the store's private means; values must already be read-only)."""
    entity.__dict__.update(values)


_ZERO3 = frozen_copy(np.zeros(3), np.float64)  # shared by the points made without a normal (it is read-only)
_NO_OBSERVATIONS: Mapping[int, int] = MappingProxyType({})
