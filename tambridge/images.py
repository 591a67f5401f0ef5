"""Image conversions shared by the exporters, the viewer and the report."""

from __future__ import annotations

import numpy as np


def rgb_uint8(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) float colours in [0, 1] (clipped) as uint8."""
    return (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
