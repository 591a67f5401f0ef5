"""Image losses of the Fusion Bridge and the mapper: masked L1, SSIM, the map loss (paper Sec. 3.4).

Images are torch tensors: colour (H, W, 3) in [0, 1], depth (H, W) metres, masks (H, W) bool. A mask selects the
pixels that take part; a loss over an empty mask is 0 (with a gradient of 0), so an all-gated view is a no-op
rather than a NaN.
"""

from __future__ import annotations

import torch
from pytorch_msssim import ssim as _ssim

SSIM_WINDOW_PX = 11
"""Gaussian window of SSIM (Wang et al. 2004; 3DGS and SplaTAM use 11 px, sigma 1.5)."""


def masked_l1(rendered: torch.Tensor, observed: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean absolute difference over the pixels where ``mask`` (H, W) holds; images (H, W) or (H, W, C).

    For (H, W, C) images the mean runs over the selected pixels and the C channels.
    """
    assert rendered.shape == observed.shape, (rendered.shape, observed.shape)
    assert mask.shape == rendered.shape[:2], (mask.shape, rendered.shape)
    difference = (rendered - observed).abs()
    if difference.dim() == 3:
        difference = difference.mean(dim=2)
    count = mask.sum()
    return torch.where(mask, difference, torch.zeros_like(difference)).sum() / count.clamp(min=1)


def ssim(rendered_rgb: torch.Tensor, observed_rgb: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two (H, W, 3) images in [0, 1] (11 px Gaussian window, valid-region mean, pytorch-msssim)."""
    assert rendered_rgb.shape == observed_rgb.shape and rendered_rgb.shape[2] == 3, (rendered_rgb.shape, observed_rgb.shape)
    height, width = rendered_rgb.shape[:2]
    window = min(SSIM_WINDOW_PX, height, width)
    window -= 1 - window % 2  # pytorch-msssim needs an odd window; tiny images get a smaller one
    to_batch = lambda image: image.permute(2, 0, 1)[None]  # noqa: E731 (N, C, H, W)
    return _ssim(to_batch(rendered_rgb), to_batch(observed_rgb.to(rendered_rgb.dtype)), data_range=1.0, win_size=window)


def map_loss(
    rendered_rgb: torch.Tensor,
    rendered_depth_m: torch.Tensor,
    observed_rgb: torch.Tensor,
    observed_depth_m: torch.Tensor,
    zeta: float,
    w_depth: float,
    w_colour: float,
) -> torch.Tensor:
    """The mapper's loss ``(1 - zeta)(w_depth L1(D) + w_colour L1(C)) + zeta (1 - SSIM(C))`` (paper Sec. 3.4).

    Depth L1 runs over the pixels with a valid observed depth (> 0: the sensor says nothing elsewhere); colour L1
    and SSIM over the whole image, so that empty space is learnt as background too.
    """
    valid_depth = observed_depth_m > 0
    everywhere = torch.ones_like(valid_depth)
    l1_depth = masked_l1(rendered_depth_m, observed_depth_m, valid_depth)
    l1_colour = masked_l1(rendered_rgb, observed_rgb, everywhere)
    return (1.0 - zeta) * (w_depth * l1_depth + w_colour * l1_colour) + zeta * (1.0 - ssim(rendered_rgb, observed_rgb))
