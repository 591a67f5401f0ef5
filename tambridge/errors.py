"""Exceptions raised on bad user input; each message names the file and the fix."""


class TambridgeError(Exception):
    """Base class of every error tambridge raises about user input or run state."""


class SequenceFormatError(TambridgeError):
    """A sequence folder, its index files or its images are missing or malformed."""


class CameraConfigError(TambridgeError):
    """Camera intrinsics or depth settings are missing, malformed or implausible."""


class TrajectoryFormatError(TambridgeError):
    """A TUM trajectory file cannot be parsed."""


class TrackingLostError(TambridgeError):
    """The frontend could not track a frame and could not recover."""


class SplatFormatError(TambridgeError):
    """A Gaussian-splat .ply file lacks the INRIA 3DGS properties or cannot be parsed."""
