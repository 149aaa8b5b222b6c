"""slamkit_scipy: the SciPy optimizer backend for slamkit (first-party plugin).

``optimizer=scipy`` solves every optimization ORB-SLAM performs (motion-only BA, local/global BA, relative
Sim3, essential-graph pose-graph optimization in Sim3/SE3) with our own Levenberg-Marquardt: iteratively
reweighted Huber, analytic vectorised Jacobians, the Schur complement for BA and scipy.sparse for the pose
graph. Nothing here imports gtsam.
"""
