"""Map entities: plain data owned by a MapStore (ORB-SLAM sec. III-C).

Ids come from the store's counters; nothing here counts or locks. Algorithm-specific scratch state lives
in the algorithms, not on these objects.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from slamkit.features import Observations
from slamkit.interfaces import BowDescription, Camera
from slamkit.map.point_table import SYNCED_ATTRIBUTES, PointTable

F64 = NDArray[np.float64]


@dataclass
class KeyFrame:
    """A keyframe (ORB-SLAM III-C).

    T_c_w: (4, 4) pose, world -> camera. features: the observation record of every keypoint of the image
    (slamkit.features.Observations: pixel, point in the pipeline's image, bearing, right coordinate, depth).
    point_ids: (N,) int64, the map point observed by each feature, -1 for none.
    bow: the bag of words of the features, once a place recognizer has described it.
    """

    id: int
    frame_index: int
    timestamp_s: float
    T_c_w: F64
    camera: Camera
    features: Observations
    point_ids: NDArray[np.int64]
    bow: BowDescription | None = None

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
        """(3,) m, the camera centre in the world frame."""
        R, t = self.T_c_w[:3, :3], self.T_c_w[:3, 3]
        return np.asarray(-R.T @ t)

    def n_tracked_points(self) -> int:
        return int(np.count_nonzero(self.point_ids >= 0))


@dataclass
class MapPoint:
    """A 3D point of the map (ORB-SLAM III-C).

    xyz_w: (3,) m, position in the world. normal_w: (3,) unit mean viewing direction (from the cameras
    observing it towards the point). descriptor: (32,) uint8, the observation descriptor with the least median
    Hamming distance to the others. d_min_m / d_max_m: the distances within which ORB's scale invariance lets
    it be observed. observations: keyframe id -> feature index in that keyframe. ref_kf_id: the keyframe that
    d_min/d_max refer to. n_visible / n_found: frames that predicted it visible / that matched it (culling
    statistic of VI-B).
    """

    id: int
    xyz_w: F64
    descriptor: NDArray[np.uint8]
    ref_kf_id: int
    first_kf_id: int
    normal_w: F64 = field(default_factory=lambda: np.zeros(3))
    d_min_m: float = 0.0
    d_max_m: float = float("inf")
    observations: dict[int, int] = field(default_factory=dict)
    n_visible: int = 1
    n_found: int = 1

    def found_ratio(self) -> float:
        return self.n_found / max(self.n_visible, 1)

    def __getstate__(self) -> dict[str, object]:
        state = dict(self.__dict__)
        state.pop("_table", None)  # a copy (pickle, deepcopy) belongs to no store
        return state

    def __setstate__(self, state: dict[str, object]) -> None:
        self.__dict__.update(state)


def _synced_attribute(name: str) -> property:
    """A MapPoint attribute that, once the point is in a store, writes every new value through to the store's
    PointTable (slamkit/map/point_table.py), from which tracking gathers thousands of points per frame."""
    slot = "_" + name

    def get(self: MapPoint) -> object:
        return self.__dict__[slot]

    def put(self: MapPoint, value: object) -> None:
        self.__dict__[slot] = value
        table = self.__dict__.get("_table")
        if table is not None:
            table.set(self.id, name, value)

    return property(get, put, doc=f"MapPoint.{name} (mirrored in the store's point table)")


for _name, _width, _dtype in SYNCED_ATTRIBUTES:
    setattr(MapPoint, _name, _synced_attribute(_name))


def mirror_in(point: MapPoint, table: PointTable | None) -> None:
    """From now on ``point``'s synced attributes are written through to ``table`` (None: to nothing)."""
    if table is None:
        point.__dict__.pop("_table", None)
    else:
        point.__dict__["_table"] = table


def mirror_of(point: MapPoint) -> PointTable | None:
    """The table ``point`` writes through to, if any."""
    table: PointTable | None = point.__dict__.get("_table")
    return table


def set_unmirrored(point: MapPoint, attribute: str, value: object) -> None:
    """Set a synced attribute on the object only: for bulk updates that write the table rows themselves."""
    point.__dict__["_" + attribute] = value
