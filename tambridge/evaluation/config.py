"""Settings of the rendering evaluation."""

from __future__ import annotations

import dataclasses

from tambridge.settings import at_least, setting


@dataclasses.dataclass
class EvaluationConfig:
    """Which frames are rendered for PSNR/SSIM/LPIPS (every n-th frame as novel views)."""

    novel_view_every: int = setting(5, "novel views: frames 0, n, 2n, ... that are not mapping views", at_least(1))
