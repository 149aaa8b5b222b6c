"""slamkit_gtsam: every optimization ORB-SLAM performs, solved with GTSAM (first-party plugin).

``optimizer=gtsam`` (or ``+backend=gtsam``). This package is the only place in slamkit that imports gtsam.
"""
