"""slamkit's embedded synthetic world: procedural textured scenes rendered with exact ground truth.

Modules: ``textures`` (seeded procedural textures, mip-maps), ``scenes`` (declarative scenes), ``trajectory``
(smooth closed camera paths with analytic derivatives), ``render`` (plane rendering with exact depth),
``imu`` (IMU simulation), ``dataset`` (``SyntheticDataset``, the ``dataset=synthetic`` config node).
"""

from slamkit.io.synthetic.dataset import SyntheticDataset
from slamkit.io.synthetic.scenes import SCENES, Scene, build_scene

__all__ = ["SCENES", "Scene", "SyntheticDataset", "build_scene"]
