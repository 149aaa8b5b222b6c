"""Real calibrations the camera tests share (importable from tests: pytest's ``pythonpath`` holds tests/).

EuRoC cam0 (radial-tangential, 4 coefficients), TUM fr1 (5, strong k3), KITTI raw camera (5, wide field), an
ideal pinhole, and TUM-VI's 512x512 fisheye (ORB-SLAM3's example KannalaBrandt8 calibration, about 190 degrees of
field of view). Intrinsics in pixels.
"""

from __future__ import annotations

from slamkit.geometry import KannalaBrandtCamera, PinholeCamera

EUROC = PinholeCamera(
    752, 480, 458.654, 457.296, 367.215, 248.375, [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
)
TUM1 = PinholeCamera(
    640, 480, 517.306408, 516.469215, 318.643040, 255.313989, [0.262383, -0.953104, -0.005358, 0.002628, 1.163314]
)
KITTI = PinholeCamera(
    1392, 512, 959.791, 956.9251, 696.0217, 224.1806, [-0.3691481, 0.1968681, 0.001353473, 0.0005677587, -0.06770705]
)
IDEAL = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)
TUMVI = KannalaBrandtCamera(
    512,
    512,
    190.97847715128717,
    190.9733070521226,
    254.93170605935475,
    256.8974428996504,
    [0.0034823894022493434, 0.0007150348452162257, -0.0020532361418706202, 0.00020293673591811182],
)
