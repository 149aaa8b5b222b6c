"""Tracking (ORB-SLAM sec. V), one module per step of the paper:

- :mod:`.motion_model` — V-B, the constant-velocity motion model (TrackWithMotionModel, UpdateLastFrame);
- :mod:`.reference_keyframe` — V-B, the fallback on the reference keyframe (TrackReferenceKeyFrame);
- :mod:`.relocalization` — V-C, relocalization when lost (Relocalization);
- :mod:`.local_map` — V-D, tracking the local map (TrackLocalMap, SearchLocalPoints);
- :mod:`.keyframe_decision` — V-E, the new-keyframe decision as a pure function (NeedNewKeyFrame);
- :mod:`.frame_pose` — the motion-only BA every step ends with (PoseOptimization);
- :mod:`.tracker` — the Tracker: the state machine that orders them.
"""

from slamkit.pipeline.outcomes import KeyFrameDecision, MappingState, TrackingOutcome, TrackingState
from slamkit.pipeline.tracking.tracker import Tracker

__all__ = ["KeyFrameDecision", "MappingState", "Tracker", "TrackingOutcome", "TrackingState"]
