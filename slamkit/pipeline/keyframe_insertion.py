"""The one keyframe inserter: how a keyframe enters the map (ORB-SLAM Map::AddKeyFrame with the observations of
LocalMapping::ProcessNewKeyFrame).

Used by initialisation for the first two keyframes of a map (slamkit/pipeline/initialization.py) and by local
mapping for every keyframe tracking makes (slamkit/pipeline/local_mapping.py). The map itself says whether a
keyframe is in it, so no flag travels with a keyframe: local mapping processes the two keyframes of a new map like
any other (as ORB-SLAM's CreateInitialMapMonocular hands them to LocalMapping::InsertKeyFrame), and inserting them
again is a no-op, as ORB-SLAM's ``mspKeyFrames.insert`` is. Called under the map's write lock.
"""

from __future__ import annotations

from slamkit.interfaces import MapStore
from slamkit.map.entities import KeyFrame
from slamkit.pipeline.map_points import refresh_points


def insert_keyframe(store: MapStore, kf: KeyFrame) -> bool:
    """Put ``kf`` in the map: the map points tracking matched to its features (``kf.point_ids``, -1 none) that are
    still in the map become its observations (``MapStore.add_keyframe``), and those points' normal, depth range and
    descriptor are refreshed. Returns False (and changes nothing) when the keyframe is in the map already."""
    if store.has_keyframe(kf.id):
        return False
    store.add_keyframe(kf)
    refresh_points(store, kf.point_ids[kf.point_ids >= 0].tolist())  # normal, depth range, descriptor
    return True
