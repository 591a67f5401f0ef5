"""Settings of the rendering evaluation."""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass
class EvaluationConfig:
    """Which frames are rendered for PSNR/SSIM/LPIPS (every n-th frame as novel views)."""

    novel_view_every: int = 5
