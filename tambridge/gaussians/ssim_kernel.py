"""Numba kernels of SSIM (Wang et al. 2004) and its exact gradient with respect to the first image: the fast twin of
pytorch-msssim's ``ssim``, which :func:`tambridge.gaussians.losses.ssim_reference` calls and the tests compare with.

The statistics are those of pytorch-msssim: a separable Gaussian window of ``k`` taps applied as a *valid*
correlation (no padding), so the SSIM map covers ``(H - k + 1, W - k + 1)`` pixels per channel, and the score is
the mean of the map over those pixels and the channels, with ``C1 = (0.01 L)^2`` and ``C2 = (0.03 L)^2``.

Where pytorch-msssim makes ten convolutions and some twenty elementwise images per call (and as many again in the
backward pass), here one pass filters the five products ``x, y, x^2, y^2, xy`` along the rows, a second along the
columns and evaluates the map and its partial derivatives in the same loop; the backward pass filters three maps
with the transposed window and combines them with the inputs. Arithmetic is float64, rows run in parallel.

Gradient. With ``m_x = G*x``, ``m_xx = G*x^2`` and ``m_xy = G*xy`` (``G*`` the valid correlation), SSIM at an output
pixel is a function of ``mu_x = m_x``, ``s_xx = m_xx - m_x^2`` and ``s_xy = m_xy - m_x m_y``, so
``dS/dx = G^T(A) + 2 x G^T(B) + y G^T(C)`` with ``B = dS/ds_xx``, ``C = dS/ds_xy`` and
``A = dS/dmu_x - 2 mu_x B - mu_y C`` (``G^T``: the transposed, *full* correlation back to the input's size).
"""

from __future__ import annotations

import numba
import numpy as np

K1, K2 = 0.01, 0.03
"""SSIM's stabilising constants (of the data range), as pytorch-msssim and the SSIM paper use them."""


@numba.njit(parallel=True, cache=True)
def ssim_forward(x: np.ndarray, y: np.ndarray, window: np.ndarray, data_range: float,
                 with_partials: bool) -> tuple[float, np.ndarray]:
    """Mean SSIM of images ``x`` and ``y`` (C, H, W) with the 1-D Gaussian ``window`` (k,), and where
    ``with_partials`` the maps (3, C, H-k+1, W-k+1) of ``A``, ``B``, ``C`` (module doc) that :func:`ssim_backward`
    takes (else an empty array)."""
    channels, height, width = x.shape
    taps = window.shape[0]
    out_h, out_w = height - taps + 1, width - taps + 1
    c1 = (K1 * data_range) ** 2
    c2 = (K2 * data_range) ** 2
    rows = np.zeros((5, channels, height, out_w))
    for task in numba.prange(channels * height):
        c, r = task // height, task % height
        # Tap by tap along the row, so that the inner loops run over contiguous pixels.
        for t in range(taps):
            w = window[t]
            for j in range(out_w):
                a = np.float64(x[c, r, j + t])
                b = np.float64(y[c, r, j + t])
                rows[0, c, r, j] += w * a
                rows[1, c, r, j] += w * b
                rows[2, c, r, j] += w * a * a
                rows[3, c, r, j] += w * b * b
                rows[4, c, r, j] += w * a * b
    partials = np.empty((3, channels, out_h, out_w)) if with_partials else np.empty((0, 0, 0, 0))
    row_sums = np.zeros(channels * out_h)
    for task in numba.prange(channels * out_h):
        c, i = task // out_h, task % out_h
        moments = np.zeros((5, out_w))
        for t in range(taps):
            w = window[t]
            for q in range(5):
                for j in range(out_w):
                    moments[q, j] += w * rows[q, c, i + t, j]
        total = 0.0
        for j in range(out_w):
            mx, my = moments[0, j], moments[1, j]
            sxx = moments[2, j] - mx * mx
            syy = moments[3, j] - my * my
            sxy = moments[4, j] - mx * my
            d1 = mx * mx + my * my + c1
            d2 = sxx + syy + c2
            luminance = (2.0 * mx * my + c1) / d1
            structure = (2.0 * sxy + c2) / d2
            total += luminance * structure
            if with_partials:
                d_mu = structure * (2.0 * my - 2.0 * mx * luminance) / d1
                d_sxx = -luminance * structure / d2
                d_sxy = 2.0 * luminance / d2
                partials[0, c, i, j] = d_mu - 2.0 * mx * d_sxx - my * d_sxy
                partials[1, c, i, j] = d_sxx
                partials[2, c, i, j] = d_sxy
        row_sums[task] = total
    return row_sums.sum() / (channels * out_h * out_w), partials


@numba.njit(parallel=True, cache=True)
def ssim_backward(x: np.ndarray, y: np.ndarray, window: np.ndarray, partials: np.ndarray,
                  grad_mean: float) -> np.ndarray:
    """Gradient (C, H, W) of ``grad_mean`` times :func:`ssim_forward`'s mean with respect to ``x``, from its
    ``partials``."""
    channels, height, width = x.shape
    taps = window.shape[0]
    out_h, out_w = partials.shape[2], partials.shape[3]
    scale = grad_mean / (channels * out_h * out_w)
    # The transposed column pass: each input row gathers the output rows its window reached.
    columns = np.zeros((3, channels, height, out_w))
    for task in numba.prange(channels * height):
        c, r = task // height, task % height
        for t in range(taps):
            i = r - t
            if i < 0 or i >= out_h:
                continue
            w = window[t] * scale
            for j in range(out_w):
                columns[0, c, r, j] += w * partials[0, c, i, j]
                columns[1, c, r, j] += w * partials[1, c, i, j]
                columns[2, c, r, j] += w * partials[2, c, i, j]
    grad = np.empty((channels, height, width))
    for task in numba.prange(channels * height):
        c, r = task // height, task % height
        sums = np.zeros((3, width))
        for t in range(taps):
            w = window[t]
            for q in range(3):
                for j in range(out_w):
                    sums[q, j + t] += w * columns[q, c, r, j]
        for p in range(width):
            grad[c, r, p] = sums[0, p] + 2.0 * np.float64(x[c, r, p]) * sums[1, p] + np.float64(y[c, r, p]) * sums[2, p]
    return grad
