"""Image conversions shared by the exporters, the viewer and the report."""

from __future__ import annotations

import cv2
import numpy as np


def rgb_uint8(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) float colours in [0, 1] (clipped) as uint8."""
    return (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


SHARPNESS_THUMBNAIL_PX = 160
"""Longer side of the grey thumbnail :func:`sharpness` measures: cheap, and blur of a few pixels survives it."""


def sharpness(rgb: np.ndarray) -> float:
    """Variance of the Laplacian of an (H, W, 3) uint8 frame's grey thumbnail (longer side
    :data:`SHARPNESS_THUMBNAIL_PX`): higher is sharper; comparable between frames of one camera only."""
    grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
    scale = SHARPNESS_THUMBNAIL_PX / max(grey.shape)
    if scale < 1.0:
        grey = cv2.resize(grey, (max(1, round(grey.shape[1] * scale)), max(1, round(grey.shape[0] * scale))),
                          interpolation=cv2.INTER_AREA)
    return float(cv2.Laplacian(grey.astype(np.float32), cv2.CV_32F).var())
