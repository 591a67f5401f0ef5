"""The numba SSIM (tambridge/gaussians/ssim_kernel.py) against its slow twin, pytorch-msssim, and finite differences."""

import numpy as np
import pytest
import torch

from benchmarks.ssim import kernel_and_twin
from tambridge.gaussians.losses import ssim, ssim_reference


def image_pair(height: int, width: int, dtype: torch.dtype, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """A textured observed image and a noisy render of it, (H, W, 3) in [0, 1]."""
    generator = torch.Generator().manual_seed(seed)
    rows, columns = torch.meshgrid(torch.arange(height, dtype=dtype), torch.arange(width, dtype=dtype), indexing="ij")
    pattern = 0.5 + 0.4 * torch.sin(rows / 3.0)[..., None] * torch.cos(columns[..., None] / 5.0 + torch.arange(3, dtype=dtype))
    observed = (pattern + 0.05 * torch.rand(height, width, 3, generator=generator, dtype=dtype)).clamp(0, 1)
    rendered = (observed + 0.1 * torch.randn(height, width, 3, generator=generator, dtype=dtype)).clamp(0, 1)
    return rendered, observed


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("size", [(120, 160), (61, 83), (30, 40), (7, 9), (4, 6)])
def test_ssim_and_its_gradient_equal_pytorch_msssim(size, dtype):
    rendered, observed = image_pair(*size, dtype)
    values, grads = kernel_and_twin(rendered, observed)
    tolerance = 1e-6 if dtype == torch.float32 else 1e-12
    assert values[0] == pytest.approx(values[1], abs=tolerance)
    assert 0.2 < values[0] < 0.99  # a real difference between the images, not a trivial 1
    assert grads[0].dtype == dtype and grads[0].shape == rendered.shape
    scale = float(grads[1].abs().max())
    assert scale > 0
    np.testing.assert_allclose(grads[0].numpy(), grads[1].numpy(), atol=(1e-5 if dtype == torch.float32 else 1e-12) * scale)


def test_ssim_gradient_matches_finite_differences():
    rendered, observed = image_pair(16, 19, torch.float64, seed=3)
    assert torch.autograd.gradcheck(lambda image: ssim(image, observed), (rendered.requires_grad_(True),),
                                    eps=1e-6, atol=1e-8)


def test_ssim_takes_the_twin_where_the_observed_image_needs_a_gradient():
    rendered, observed = image_pair(20, 24, torch.float64, seed=5)
    observed.requires_grad_(True)
    ssim(rendered, observed).backward()
    reference = observed.detach().clone().requires_grad_(True)
    ssim_reference(rendered, reference).backward()
    np.testing.assert_allclose(observed.grad.numpy(), reference.grad.numpy(), atol=1e-14)

