"""Image losses of the Fusion Bridge and the mapper: masked L1, SSIM, the map loss (paper Sec. 3.4).

Images are torch tensors: colour (H, W, 3) in [0, 1], depth (H, W) metres, masks (H, W) bool. A mask selects the
pixels that take part; a loss over an empty mask is 0 (with a gradient of 0), so an all-gated view is a no-op
rather than a NaN.
"""

from __future__ import annotations

import functools

import numpy as np
import torch
from pytorch_msssim import ssim as _ssim
from torch.autograd.function import once_differentiable

from tambridge.gaussians import ssim_kernel

SSIM_WINDOW_PX = 11
"""Gaussian window of SSIM (Wang et al. 2004; 3DGS and SplaTAM use 11 px, sigma 1.5)."""
SSIM_SIGMA_PX = 1.5


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
    """Mean SSIM of two (H, W, 3) images in [0, 1] (11 px Gaussian window, valid-region mean), differentiable with
    respect to ``rendered_rgb``: the numba kernels of :mod:`tambridge.gaussians.ssim_kernel` on the CPU, else
    (a CUDA tensor, or ``observed_rgb`` that needs a gradient too) :func:`ssim_reference`, which they equal."""
    assert rendered_rgb.shape == observed_rgb.shape and rendered_rgb.shape[2] == 3, (rendered_rgb.shape, observed_rgb.shape)
    if rendered_rgb.device.type != "cpu" or observed_rgb.requires_grad:
        return ssim_reference(rendered_rgb, observed_rgb)
    return _CpuSsim.apply(rendered_rgb, observed_rgb)


def ssim_reference(rendered_rgb: torch.Tensor, observed_rgb: torch.Tensor) -> torch.Tensor:
    """:func:`ssim` by pytorch-msssim (any device, gradients to both images): the slow twin of the numba kernels."""
    window = ssim_window_size(*rendered_rgb.shape[:2])
    to_batch = lambda image: image.permute(2, 0, 1)[None]  # noqa: E731 (N, C, H, W)
    return _ssim(to_batch(rendered_rgb), to_batch(observed_rgb.to(rendered_rgb.dtype)), data_range=1.0, win_size=window,
                 win_sigma=SSIM_SIGMA_PX)


def ssim_window_size(height: int, width: int) -> int:
    """Taps of the SSIM window for an image of ``height`` x ``width``: 11, or for tiny images the largest odd size
    that fits (pytorch-msssim needs an odd window)."""
    window = min(SSIM_WINDOW_PX, height, width)
    return window - (1 - window % 2)


@functools.lru_cache(maxsize=None)
def ssim_window(taps: int) -> np.ndarray:
    """The 1-D Gaussian window (taps,) float64, normalised, computed in float32 as pytorch-msssim computes it.
    Made once per size (every mapping step asks for it) and read-only, since callers share it."""
    coords = torch.arange(taps, dtype=torch.float32) - taps // 2
    weights = torch.exp(-(coords ** 2) / (2 * SSIM_SIGMA_PX ** 2))
    window = (weights / weights.sum()).to(torch.float64).numpy()
    window.flags.writeable = False
    return window


class _CpuSsim(torch.autograd.Function):
    """Autograd wrapper of :mod:`ssim_kernel`: the gradient goes to the rendered image only."""

    @staticmethod
    def forward(ctx, rendered_rgb, observed_rgb):
        to_planes = lambda image: np.ascontiguousarray(  # noqa: E731 (C, H, W), float32 or float64 as given
            image.detach().to(rendered_rgb.dtype if rendered_rgb.dtype == torch.float64 else torch.float32)
            .permute(2, 0, 1).numpy())
        rendered, observed = to_planes(rendered_rgb), to_planes(observed_rgb)
        window = ssim_window(ssim_window_size(*rendered_rgb.shape[:2]))
        value, partials = ssim_kernel.ssim_forward(rendered, observed, window, 1.0, rendered_rgb.requires_grad)
        ctx.kernel_inputs = (rendered, observed, window, partials)
        ctx.dtype = rendered_rgb.dtype
        return torch.tensor(value, dtype=rendered_rgb.dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_value):
        rendered, observed, window, partials = ctx.kernel_inputs
        grad = ssim_kernel.ssim_backward(rendered, observed, window, partials, float(grad_value))
        return torch.from_numpy(grad).permute(1, 2, 0).to(ctx.dtype), None


def map_loss(
    rendered_rgb: torch.Tensor,
    rendered_depth_m: torch.Tensor,
    observed_rgb: torch.Tensor,
    observed_depth_m: torch.Tensor,
    zeta: float,
    w_depth: float,
    w_colour: float,
    w_colour_squared: float = 0.0,
) -> torch.Tensor:
    """The mapper's loss ``(1 - zeta)(w_depth L1(D) + w_colour L1(C) + w_colour_squared MSE(C)) + zeta (1 - SSIM(C))``
    (paper Sec. 3.4, which has no squared term: ``w_colour_squared`` 0).

    Depth L1 runs over the pixels with a valid observed depth (> 0: the sensor says nothing elsewhere); the colour
    terms and SSIM over the whole image, so that empty space is learnt as background too. MSE is the mean over
    pixels and channels; where frames disagree on a surface's colour it pulls towards their mean, which is what
    PSNR rewards, where L1 settles on their median.
    """
    l1_depth = masked_l1(rendered_depth_m, observed_depth_m, observed_depth_m > 0)
    colour_difference = rendered_rgb - observed_rgb
    colour = w_colour * colour_difference.abs().mean()
    if w_colour_squared:
        colour = colour + w_colour_squared * colour_difference.square().mean()
    return (1.0 - zeta) * (w_depth * l1_depth + colour) + zeta * (1.0 - ssim(rendered_rgb, observed_rgb))
