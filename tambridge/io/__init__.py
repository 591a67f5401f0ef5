"""Sequence readers (TUM RGB-D layout) and synthetic sequences with exact ground truth."""

from tambridge.io.tum import Frame, RgbdSequence, open_sequence

__all__ = ["Frame", "RgbdSequence", "open_sequence"]
