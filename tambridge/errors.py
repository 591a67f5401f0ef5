"""Exceptions raised on bad user input; each message names the file and the fix."""

INPUT_ERROR_STATUS = 2
"""The exit status of a command stopped by one of these errors (or by click's usage errors)."""


class TambridgeError(Exception):
    """Base class of every error tambridge raises about user input or run state."""


class SequenceFormatError(TambridgeError):
    """A sequence folder, its index files or its images are missing or malformed."""


class CameraConfigError(TambridgeError):
    """Camera intrinsics or depth settings are missing, malformed or implausible."""


class TrajectoryFormatError(TambridgeError):
    """A TUM trajectory file cannot be parsed."""


class ConfigError(TambridgeError):
    """A preset or override names an unknown key or gives a value of the wrong type or range."""


class CheckpointError(TambridgeError):
    """A checkpoint is missing, unreadable, of another version, or of another config or sequence."""


class SplatFormatError(TambridgeError):
    """A Gaussian-splat .ply file lacks the INRIA 3DGS properties or cannot be parsed."""


class TrajectoryEvaluationError(TambridgeError, ValueError):
    """A trajectory cannot be compared with its ground truth: too few poses share its clock, or they cannot be
    aligned (too few, or all on a line)."""


class ExportError(TambridgeError):
    """A run folder cannot be exported (results or sequence missing, a model the target format cannot hold)."""


class TrackingFailedError(TambridgeError):
    """No frame after the first could be tracked: the run has no trajectory to give (images without texture or
    depth, a wrong camera)."""


class ViewerError(TambridgeError):
    """A run's splat viewer cannot be served: the folder is no finished run, has no viewer, or the port is taken."""
