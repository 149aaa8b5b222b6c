"""slamkit: a plugin-based framework for feature-based visual SLAM, faithful to ORB-SLAM.

The core (this package) defines the interfaces, the plugin system, geometry, map entities, the pipeline
and the runtime. Components (feature extractors, place recognizers, initializers, optimizers, datasets)
are registered by plugins through the ``slamkit`` entry-point group; see ``slamkit.plugins``.

The Python API (slamkit/api.py, docs/api.md) is re-exported here: ``slamkit.open_system(overrides)`` gives a
``System`` to feed frames to. It is imported on first use, so ``import slamkit`` (and every ``slamkit`` command)
stays light.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

if TYPE_CHECKING:
    from slamkit.api import FrameInputError, FrameResult, MapData, System, SystemClosedError, open_system

#: The names of slamkit.api re-exported here.
_API = ("FrameInputError", "FrameResult", "MapData", "System", "SystemClosedError", "open_system")

__all__ = [
    "FrameInputError",
    "FrameResult",
    "MapData",
    "System",
    "SystemClosedError",
    "__version__",
    "open_system",
]


def __getattr__(name: str) -> Any:
    """``slamkit.open_system`` and the other names of slamkit.api, imported on first use (PEP 562)."""
    if name in _API:
        import slamkit.api

        return getattr(slamkit.api, name)
    raise AttributeError(f"module 'slamkit' has no attribute {name!r}")
