"""The Atlas of ORB-SLAM3 (T-RO 2021, sec. I and III; released code: Atlas.cc, KeyFrameDatabase.cc): several maps,
one of them active, keyframe and map point ids unique across all of them, and one keyframe database (the place
recognizer) shared by all of them.

Tracking, local mapping and loop closing work on the *active* map (``Atlas.active``); the other maps stay in the
Atlas untouched until loop closing merges one of them into the active map (:meth:`Atlas.absorb`). A map is never deleted because tracking was lost: when tracking
gives up on a map that is big enough, :meth:`Atlas.create_map` starts a new active map and keeps the old one
(ORB-SLAM3 Tracking::CreateMapInAtlas -> Atlas::CreateNewMap). A map too small to keep is reset instead
(:meth:`Atlas.reset_active`, ORB-SLAM3 System::ResetActiveMap): its keyframes are erased, from the map and from
the keyframe database.

Ids. Every map is a MapStore built by the configured ``map=`` component through the factory the app hands the
Atlas, all with the Atlas's one IdAllocator, so a keyframe id names one keyframe in the whole Atlas and the place
recognizer can stay keyed on keyframe ids; :meth:`Atlas.map_of` answers which map a keyframe belongs to. Map ids
are monotonic from 0 and never reused.

Threads. The active map changes only from the tracking thread, when the runner carries out the tracker's
``lost_decision`` with local mapping and loop closing parked; the other threads read ``active`` per step. Maps
other than the active one are not changed by anyone, so reading them needs no lock.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from enum import StrEnum
from typing import TYPE_CHECKING

from slamkit.errors import ConfigError, SlamkitError
from slamkit.interfaces import MapStore, PlaceRecognizer
from slamkit.map.ids import IdAllocator
from slamkit.sensors import FrameRecords

if TYPE_CHECKING:
    from slamkit.map.mapfile_contents import MapContents

#: Builds one empty map whose ids come from the given allocator (the app: the configured ``map=`` component).
StoreFactory = Callable[[IdAllocator], MapStore]


class MapChange(StrEnum):
    """How the active map changed between two moments (see :meth:`Atlas.change_since`)."""

    RESET = "reset"  # the active map's keyframes were erased; the emptied map goes on under a new id
    NEW_MAP = "new_map"  # a new active map was started; the previous one stays in the Atlas


class Atlas:
    """The maps of a run, the active one, and the keyframe database across them.

    new_store: builds an empty map with the Atlas's IdAllocator (called for the first map now and for each new
    map later; None: the Atlas holds ``first`` only and cannot start another map). place: the keyframe database
    shared by every map (None: no place recognition). first: an existing store to use as map 0 (its IdAllocator
    becomes the Atlas's), e.g. a map a test built by hand.
    """

    def __init__(
        self,
        new_store: StoreFactory | None,
        place: PlaceRecognizer | None = None,
        first: MapStore | None = None,
    ) -> None:
        if new_store is None and first is None:
            raise ValueError("Atlas: give new_store (a factory of maps) or first (the one map)")
        self._new_store = new_store
        self.ids = first.ids if first is not None else IdAllocator()
        self.place = place
        self._maps: dict[int, MapStore] = {}
        self._next_map_id = 0
        self._active_id = self._add(first if first is not None else self._build())
        #: map id -> the frames of earlier sessions a map file kept for that map (slamkit/map/mapfile.py; empty for
        #: an Atlas not loaded from a file): the runners' trajectory recorders start from them (docs/atlas.md,
        #: "Multi-session"). As loaded: nothing updates it during a run.
        self.loaded_frames: dict[int, FrameRecords] = {}

    @classmethod
    def of(cls, store: MapStore, place: PlaceRecognizer | None = None) -> Atlas:
        """An Atlas of one given map that cannot start another (tests, notebooks)."""
        return cls(None, place, first=store)

    @classmethod
    def restore(
        cls,
        new_store: StoreFactory,
        place: PlaceRecognizer | None,
        ids: IdAllocator,
        maps: Sequence[tuple[int, MapContents]],
        active_id: int,
        next_map_id: int,
    ) -> Atlas:
        """The Atlas of a saved map file (slamkit/map/mapfile.py): each (map id, contents) restored into a new store
        built by ``new_store`` with ``ids`` (the saved allocator's state), under its saved map id; ``active_id`` the
        active map; ``next_map_id`` the id the next new map gets. Then every keyframe with a bag of words goes into
        the keyframe database ``place``, map by map in ascending keyframe ids. ValueError (nothing added to
        ``place``) when the maps do not fit together: no map, an unknown active map, a map id at or above
        ``next_map_id``, or contents a store refuses (MapStore.restore)."""
        if not maps:
            raise ValueError("an Atlas needs at least one map")
        map_ids = [m for m, _ in maps]
        if len(set(map_ids)) != len(map_ids) or min(map_ids) < 0 or max(map_ids) >= next_map_id:
            raise ValueError(f"map ids {map_ids} are not distinct ids below the next map id {next_map_id}")
        if active_id not in map_ids:
            raise ValueError(f"the active map {active_id} is not one of the maps {map_ids}")
        atlas = cls.__new__(cls)
        atlas._new_store = new_store
        atlas.ids = ids
        atlas.place = place
        atlas._maps = {}
        for map_id, contents in maps:
            store = atlas._build()
            store.restore(contents)
            atlas._maps[map_id] = store
        atlas._next_map_id = next_map_id
        atlas._active_id = active_id
        atlas.loaded_frames = {}
        if place is not None:
            for _, contents in sorted(maps, key=lambda mc: mc[0]):
                for kf in contents.keyframes:
                    if kf.bow is not None:
                        place.add(kf.id, kf.bow)
        return atlas

    # ---- the maps ----------------------------------------------------------------------------------

    @property
    def active(self) -> MapStore:
        """The map tracking, local mapping and loop closing work on."""
        return self._maps[self._active_id]

    @property
    def active_id(self) -> int:
        return self._active_id

    @property
    def next_map_id(self) -> int:
        """The id the next new map gets (map ids are never reused)."""
        return self._next_map_id

    def map_ids(self) -> list[int]:
        """Every map's id, ascending (creation order)."""
        return sorted(self._maps)

    def get(self, map_id: int) -> MapStore:
        """The map ``map_id`` (KeyError when the Atlas has no such map)."""
        return self._maps[map_id]

    def items(self) -> list[tuple[int, MapStore]]:
        """(map id, map) of every map, ascending ids."""
        return sorted(self._maps.items())

    def __len__(self) -> int:
        return len(self._maps)

    def map_of(self, keyframe_id: int) -> int | None:
        """The id of the map holding ``keyframe_id`` (None: no map holds it, e.g. it was culled or erased)."""
        if self.active.has_keyframe(keyframe_id):
            return self._active_id
        for map_id, store in list(self._maps.items()):  # a copy: safe against a map added meanwhile
            if map_id != self._active_id and store.has_keyframe(keyframe_id):
                return map_id
        return None

    def best_neighbors(self, keyframe_id: int, n: int) -> list[int]:
        """A keyframe's ``n`` best covisible keyframes in its own map (the grouping of place-recognition
        candidates, which may come from any map, ORB-SLAM3 KeyFrameDatabase::DetectRelocalizationCandidates).
        A keyframe no map holds has the active map's answer (none)."""
        map_id = self.map_of(keyframe_id)
        store = self.active if map_id is None else self._maps[map_id]
        return store.covisibility.best_neighbors(keyframe_id, n)

    def keyframes_outside_active(self) -> set[int]:
        """Ids of the keyframes of every map but the active one (loop detection leaves them out: ORB-SLAM3
        KeyFrameDatabase::DetectLoopCandidates counts only keyframes "in the same map")."""
        active = self._active_id
        return {k for map_id, store in self.items() if map_id != active for k in store.keyframe_ids()}

    # ---- changes (tracking thread, workers parked) ---------------------------------------------------------------

    def create_map(self) -> int:
        """Start a new, empty active map; the previous active map stays in the Atlas as it is (ORB-SLAM3
        Atlas::CreateNewMap). Returns the new map's id."""
        self._active_id = self._add(self._build())
        return self._active_id

    def reset_active(self) -> int:
        """Erase the active map's keyframes, from the map and from the keyframe database (ORB-SLAM3
        System::ResetActiveMap: KeyFrameDatabase::clearMap, Atlas::clearMap). The emptied map goes on as the active
        map under a new id, so each map id is initialised once (one ``slamkit_map_created``). Returns that id."""
        store = self.active
        with store.write():
            for kf_id in store.keyframe_ids():
                store.remove_keyframe(kf_id)
                if self.place is not None:
                    self.place.remove(kf_id)
        del self._maps[self._active_id]
        self._active_id = self._add(store)
        return self._active_id

    def absorb(self, map_id: int) -> None:
        """Map merging (ORB-SLAM3 MergeLocal; slamkit/pipeline/map_merging.py) moved every keyframe and point of the
        map ``map_id`` into the active map: the map leaves the Atlas (ORB-SLAM3 Atlas::SetMapBad, RemoveBadMaps). Its
        keyframes keep their ids, so the keyframe database needs no change. Called by loop closing under the active
        map's write lock; ValueError for the active map or an unknown one."""
        if map_id == self._active_id or map_id not in self._maps:
            raise ValueError(f"map {map_id} cannot be absorbed into the active map {self._active_id}")
        del self._maps[map_id]

    def change_since(self, map_id: int) -> MapChange | None:
        """How the active map changed since ``map_id`` was the active one: None (it still is), RESET (that map
        was reset: its id is gone) or NEW_MAP (it stays in the Atlas, another map is active)."""
        if map_id == self._active_id:
            return None
        return MapChange.NEW_MAP if map_id in self._maps else MapChange.RESET

    # ---- internals ------------------------------------------------------------------------------

    def _build(self) -> MapStore:
        if self._new_store is None:
            raise SlamkitError("this Atlas was given one map and no factory of maps: it cannot start another map")
        store = self._new_store(self.ids)
        if store.ids is not self.ids:
            raise ConfigError(
                f"map: the store {type(store).__name__} ignores the id allocator it is built with (ids=...): the maps "
                "of an Atlas need ids unique across them"
            )
        return store

    def _add(self, store: MapStore) -> int:
        map_id = self._next_map_id
        self._next_map_id += 1
        self._maps[map_id] = store
        return map_id


__all__ = ["Atlas", "MapChange", "StoreFactory"]
