"""Front ends: turn a sensor packet into a frame's per-keypoint observation record (``slamkit.features.Observations``).

``frontend=mono`` (``MonocularFrontEnd``) is the one built now; stereo and RGB-D front ends plug in through the
same ``slamkit.interfaces.FrontEnd`` protocol and fill the record's right coordinate and depth.
"""
