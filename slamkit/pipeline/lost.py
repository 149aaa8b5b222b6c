"""What tracking does when it is lost (ORB-SLAM3, visual-only, released code v1.0 Tracking::Track).

A frame that cannot be tracked puts tracking in ORB-SLAM3's RECENTLY_LOST state: the next frames try to
relocalize in the active map. If the map is small (``reset_lost_map_max_keyframes``, ORB-SLAM3: 10 keyframes,
``KeyFramesInMap() <= 10``) there is little to lose and it is reset at once: its keyframes are erased and
initialisation starts again (ORB-SLAM3 System::ResetActiveMap; ORB-SLAM2 did the same with 5 keyframes). A bigger
map is kept: relocalization is tried for ``time_recently_lost_s`` seconds of the sequence (ORB-SLAM3: 3 s for a
visual-only system, ``mCurrentFrame.mTimeStamp - mTimeStampLost > 3.0f``; its ``time_recently_lost`` of 5 s is the
visual-inertial limit); when the first frame after that also fails, tracking is LOST and a new active map starts,
the old one staying in the Atlas (Tracking::CreateMapInAtlas).

One simplification: ORB-SLAM3 also lets a small map (at most 10 keyframes) that was lost while tracking the local
map try to relocalize for 3 s before resetting it; here a small map is reset on its first lost frame, whichever
step failed (as ORB-SLAM2 and slamkit before the Atlas did).

In localization mode (``mode=localization``, ORB-SLAM2/3's mbOnlyTracking) the map is read-only: it is neither reset
nor replaced, and tracking keeps relocalizing in it for as long as it takes (``LostPolicy.map_read_only``). ORB-SLAM2
would still reset a map of at most 5 keyframes there (the reset check after Track's two branches), and ORB-SLAM3's
localization branch never reaches its LOST state (RECENTLY_LOST turns LOST only in the mapping branch); neither fits a
map loaded to be used as it is.

The decision is a pure function of a small record, :func:`decide_when_lost`.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum


class LostDecision(StrEnum):
    RELOCALIZE = "relocalize"  # recently lost: keep trying to relocalize in the active map
    RESET_MAP = "reset_map"  # erase the (small) active map and initialise again
    NEW_MAP = "new_map"  # keep the active map in the Atlas and initialise a new one


@dataclass(frozen=True)
class LostRecord:
    """Where tracking stands on a frame it could not track.

    keyframes_in_map: keyframes of the active map. lost_for_s: sequence time since the first frame of this lost
    spell (0 on that frame), s.
    """

    keyframes_in_map: int
    lost_for_s: float


@dataclass(frozen=True)
class LostPolicy:
    """The two constants (``pipeline.tracking``): ``reset_lost_map_max_keyframes`` (ORB-SLAM3: 10) and
    ``time_recently_lost_s`` (ORB-SLAM3 visual-only: 3 s); map_read_only: localization mode, the map is never reset
    or replaced (always RELOCALIZE)."""

    reset_lost_map_max_keyframes: int = 10
    time_recently_lost_s: float = 3.0
    map_read_only: bool = False


def decide_when_lost(record: LostRecord, policy: LostPolicy) -> LostDecision:
    """ORB-SLAM3's choice for a frame tracking could not track (see the module docstring)."""
    if policy.map_read_only:
        return LostDecision.RELOCALIZE
    if record.keyframes_in_map <= policy.reset_lost_map_max_keyframes:
        return LostDecision.RESET_MAP
    if record.lost_for_s > policy.time_recently_lost_s:
        return LostDecision.NEW_MAP
    return LostDecision.RELOCALIZE


__all__ = ["LostDecision", "LostPolicy", "LostRecord", "decide_when_lost"]
