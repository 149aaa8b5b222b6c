"""Exception types raised by slamkit. Each names the file/parameter/plugin at fault and what was expected."""

from __future__ import annotations


class SlamkitError(Exception):
    """Base class of every error slamkit raises on purpose."""


class DatasetError(SlamkitError):
    """Bad dataset input: a missing or malformed file. The message names the file (and line) at fault."""


class FrameReadError(DatasetError):
    """One frame's file is missing, cannot be decoded or is damaged (a truncated JPEG); the run may skip the frame
    (``runner.bad_frames``). The message names the file."""


class CalibrationError(DatasetError):
    """A calibration that is missing, malformed, or disagrees with the images."""


class PluginError(SlamkitError):
    """A plugin that failed to load, implements no hook, or returned a component of the wrong kind."""


class ConfigError(SlamkitError):
    """A configuration value that is missing or outside its valid range; names the config key."""


class ExportError(SlamkitError):
    """A map that cannot be exported as asked (unknown format or map, an unreadable source, an unwritable output);
    names the path or the option at fault."""


class ProblemError(SlamkitError):
    """An optimization problem that is malformed (NaN/inf, empty, degenerate) and was not sent to a solver."""


class EvaluationError(SlamkitError):
    """Trajectories that cannot be compared (too few poses matched in time, degenerate alignment, ...)."""


class MapFileError(SlamkitError):
    """A map file that cannot be written or read: an unwritable path, a truncated or corrupted file (checksum), another
    schema version, a vocabulary unlike the run's. The message names the file and what is wrong; nothing was loaded."""
