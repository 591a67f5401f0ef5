"""Rendering quality: PSNR, SSIM and LPIPS of rendered frames against the input frames.

Images are (H, W, 3) float arrays or tensors in [0, 1]. PSNR is over all pixels and channels with a peak of 1;
SSIM is the standard 11 px Gaussian-window SSIM (as in 3DGS, SplaTAM and the paper's tables).

LPIPS (Zhang et al. 2018, AlexNet backbone) needs pretrained weights that no pip wheel ships: the ``lpips``
package carries its linear heads but takes the AlexNet backbone from torchvision's download cache. There is no
network at run time, so LPIPS is computed only when ``lpips`` and ``torchvision`` import and the AlexNet
checkpoint is already in the torch hub cache; otherwise it is None and a warning says why (never a made-up number).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np
import torch

from tambridge.gaussians.losses import ssim as ssim_tensor
from tambridge.io.tum import RgbdSequence

logger = logging.getLogger("tambridge.evaluation.rendering")

ALEXNET_CHECKPOINT = "alexnet-owt-7be5be79.pth"
"""File name of torchvision's ImageNet AlexNet weights in the torch hub cache (what ``lpips`` loads)."""


def _as_tensor(image) -> torch.Tensor:
    return torch.as_tensor(np.asarray(image) if not isinstance(image, torch.Tensor) else image).to(torch.float64)


def psnr_db(rendered_rgb, observed_rgb) -> float:
    """Peak signal-to-noise ratio, dB, of two (H, W, 3) images in [0, 1]: ``-10 log10(MSE)`` (inf when equal)."""
    rendered, observed = _as_tensor(rendered_rgb), _as_tensor(observed_rgb)
    assert rendered.shape == observed.shape, (rendered.shape, observed.shape)
    mse = float(((rendered - observed) ** 2).mean())
    return float("inf") if mse == 0.0 else -10.0 * float(np.log10(mse))


def ssim_value(rendered_rgb, observed_rgb) -> float:
    """SSIM of two (H, W, 3) images in [0, 1]."""
    # In float32: its windowed means agree with float64 far below SSIM's precision and CPU convolutions run
    # several times faster, and SSIM was most of a run's evaluation time.
    return float(ssim_tensor(_as_tensor(rendered_rgb).to(torch.float32), _as_tensor(observed_rgb).to(torch.float32)))


@functools.lru_cache(maxsize=1)
def lpips_model() -> Callable | None:
    """The LPIPS (AlexNet) network when its weights are installed locally, else None (with a warning, once)."""
    try:
        import lpips  # noqa: F401  (optional: not a dependency of tambridge)
        import torchvision  # noqa: F401
    except ImportError:
        logger.warning("LPIPS not computed: the 'lpips' and 'torchvision' packages are not installed "
                       "(pip install lpips torchvision, and place %s in the torch hub cache)", ALEXNET_CHECKPOINT)
        return None
    checkpoint = Path(torch.hub.get_dir()) / "checkpoints" / ALEXNET_CHECKPOINT
    if not checkpoint.is_file():
        logger.warning("LPIPS not computed: AlexNet weights %s are not installed and cannot be downloaded at run time",
                       checkpoint)
        return None
    import lpips

    model = lpips.LPIPS(net="alex", verbose=False).eval()
    return model


def lpips_value(rendered_rgb, observed_rgb) -> float | None:
    """LPIPS (AlexNet) of two (H, W, 3) images in [0, 1]; None when the weights are not installed."""
    model = lpips_model()
    if model is None:
        return None
    to_batch = lambda image: (_as_tensor(image).to(torch.float32).permute(2, 0, 1)[None] * 2.0 - 1.0)  # noqa: E731
    with torch.no_grad():
        return float(model(to_batch(rendered_rgb), to_batch(observed_rgb)))


@dataclasses.dataclass
class RenderingScores:
    """Per-frame scores of a set of rendered frames and their means (LPIPS None when unavailable)."""

    frame_indices: list[int]
    psnr_db: list[float]
    ssim: list[float]
    lpips: list[float] | None

    def summary(self) -> dict:
        """Means and the frame count, as written to metrics.json."""
        return {
            "frames": len(self.frame_indices),
            "psnr_db": float(np.mean(self.psnr_db)) if self.psnr_db else None,
            "ssim": float(np.mean(self.ssim)) if self.ssim else None,
            "lpips": float(np.mean(self.lpips)) if self.lpips else None,
        }


def score_renders(pairs: Iterable[tuple[int, np.ndarray, np.ndarray]]) -> RenderingScores:
    """Score ``(frame_index, rendered_rgb, observed_rgb)`` triples (images (H, W, 3) in [0, 1])."""
    indices, psnrs, ssims, lpipses = [], [], [], []
    for index, rendered, observed in pairs:
        indices.append(index)
        psnrs.append(psnr_db(rendered, observed))
        ssims.append(ssim_value(rendered, observed))
        lpipses.append(lpips_value(rendered, observed))
    lpips = None if any(value is None for value in lpipses) else lpipses
    return RenderingScores(indices, psnrs, ssims, lpips)


def reference_rgb(sequence: RgbdSequence, index: int, sharp: bool = True) -> np.ndarray:
    """What a render of frame ``index`` is scored against, (H, W, 3) uint8: its sharp ground-truth image where the
    sequence has them (``gt_rgb/``, synthetic blurred sequences) and ``sharp``, else the input frame."""
    return sequence.sharp_rgb(index) if sharp and sequence.has_sharp_rgb else sequence[index].rgb


def score_frames(sequence: RgbdSequence, render_rgb: Callable[[int], torch.Tensor],
                 frame_indices: list[int], against_sharp: bool = True) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """``(frame_index, rendered, observed)`` for :func:`score_renders`: ``render_rgb(frame_index)`` (H, W, 3) at the
    sequence's full resolution, clipped to [0, 1], and the frame's :func:`reference_rgb`, both cut to the
    sequence's valid region (undistortion's border, where the frames have no data, is not scored)."""
    top, bottom, left, right = sequence.valid_region
    for index in frame_indices:
        with torch.no_grad():
            rendered = render_rgb(index).clamp(0.0, 1.0).cpu().numpy()[top:bottom, left:right]
        reference = reference_rgb(sequence, index, against_sharp)
        yield index, rendered, reference[top:bottom, left:right].astype(np.float32) / 255.0
