"""Which frames of a sequence are read."""

from __future__ import annotations

import dataclasses

from tambridge.settings import at_least, setting


@dataclasses.dataclass
class InputConfig:
    """Which frames of the sequence are read."""

    stride: int = setting(1, "read every n-th frame of the sequence", at_least(1))
    max_frames: int | None = setting(None, "read at most this many frames (after the stride; null: all)", at_least(1))
    camera_file: str | None = setting(None, "camera.yaml/camera.txt for a non-TUM camera (null: the sequence's own or a TUM preset)")
