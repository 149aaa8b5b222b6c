"""slamkit: a plugin-based framework for feature-based visual SLAM, faithful to ORB-SLAM.

The core (this package) defines the interfaces, the plugin system, geometry, map entities, the pipeline
and the runtime. Components (feature extractors, place recognizers, initializers, optimizers, datasets)
are registered by plugins through the ``slamkit`` entry-point group; see ``slamkit.plugins``.
"""

__version__ = "0.1.0"
