"""Which frames of a sequence are read."""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass
class InputConfig:
    """Which frames of the sequence are read."""

    stride: int = 1
    max_frames: int | None = None
    camera_file: str | None = None
