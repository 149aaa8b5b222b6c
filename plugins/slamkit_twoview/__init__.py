"""slamkit_twoview: ORB-SLAM's two-view map initializer (Mur-Artal et al. T-RO 2015, sec. IV), first-party plugin.

``initializer=twoview`` fits a homography and a fundamental matrix by RANSAC on shared minimal sets,
picks one by the ratio of their scores, recovers the motion hypotheses (Faugeras' 8 from H, 4 from E)
and accepts the reconstruction only when one hypothesis is a clear winner with enough parallax.
"""

from slamkit_twoview.initializer import TwoViewInitializer

__all__ = ["TwoViewInitializer"]
