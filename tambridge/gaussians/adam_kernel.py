"""The mapper's Adam step on the CPU in one numba pass over the Gaussians (:meth:`GaussianMap._adam_step`).

The torch step (:func:`tambridge.gaussians.mapper.adam_step_torch`, the twin the tests compare with, and the path on
a GPU) makes about a dozen passes over every field with a temporary each, on the mapper's one torch thread; this
kernel reads and writes each Gaussian's parameters, gradients and moments once, in parallel over Gaussians. The
arithmetic is float64 on float32 storage, so the two agree to float32 rounding, not to the bit.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from tambridge.gaussians.model import FIELDS


@numba.njit(cache=True, inline="always")
def _has_gradient(row, grad):
    for column in range(grad.shape[1]):
        if grad[row, column] != 0.0:
            return True
    return False


@numba.njit(cache=True, inline="always")
def _step_field(row, param, grad, exp_avg, exp_avg_sq, beta1, beta2, step_size, root_correction, eps):
    for column in range(param.shape[1]):
        gradient = grad[row, column]
        first = beta1 * exp_avg[row, column] + (1.0 - beta1) * gradient
        second = beta2 * exp_avg_sq[row, column] + (1.0 - beta2) * gradient * gradient
        exp_avg[row, column] = first
        exp_avg_sq[row, column] = second
        param[row, column] -= step_size * first / (math.sqrt(second) * root_correction + eps)


@numba.njit(parallel=True, cache=True)
def _adam(means, rgb, log_radii, opacity, grad_means, grad_rgb, grad_log_radii, grad_opacity,
          avg_means, avg_rgb, avg_log_radii, avg_opacity, sq_means, sq_rgb, sq_log_radii, sq_opacity,
          steps, learning_rates, beta1, beta2, eps, inverse_corrections1, root_corrections2):
    for row in numba.prange(steps.shape[0]):
        if (_has_gradient(row, grad_means) or _has_gradient(row, grad_rgb) or _has_gradient(row, grad_log_radii)
                or _has_gradient(row, grad_opacity)):
            step = int(steps[row]) + 1
            steps[row] = step
            inverse_correction1 = inverse_corrections1[step]
            root_correction = root_corrections2[step]
            _step_field(row, means, grad_means, avg_means, sq_means, beta1, beta2,
                        learning_rates[0] * inverse_correction1, root_correction, eps)
            _step_field(row, rgb, grad_rgb, avg_rgb, sq_rgb, beta1, beta2,
                        learning_rates[1] * inverse_correction1, root_correction, eps)
            _step_field(row, log_radii, grad_log_radii, avg_log_radii, sq_log_radii, beta1, beta2,
                        learning_rates[2] * inverse_correction1, root_correction, eps)
            _step_field(row, opacity, grad_opacity, avg_opacity, sq_opacity, beta1, beta2,
                        learning_rates[3] * inverse_correction1, root_correction, eps)
        # Colours (the second of model.FIELDS) are kept in the displayable range (every row, as the torch step clamps).
        for column in range(3):
            rgb[row, column] = min(max(rgb[row, column], 0.0), 1.0)


def _columns(tensor: torch.Tensor) -> np.ndarray:
    """(M, C) numpy view of a CPU tensor (M,) or (M, C): writes go to the tensor (``view`` refuses a copy)."""
    return tensor.view(tensor.shape[0], -1).numpy()


def adam_step_numba(params: dict, grads: dict, exp_avg: dict, exp_avg_sq: dict, steps: torch.Tensor,
                    learning_rates: dict[str, float], betas: tuple[float, float], eps: float) -> torch.Tensor:
    """In place on ``params``, ``exp_avg`` and ``exp_avg_sq`` (dicts of CPU float32 tensors (M, ...) by field,
    contiguous): one Adam step on every Gaussian with a nonzero gradient in some field of ``grads``, at
    ``learning_rates`` by field; the others keep their parameters and moments. Returns the new step counts (M,)."""
    steps = steps.clone()
    arrays = [_columns(table[name]) for table in (params, grads, exp_avg, exp_avg_sq) for name in FIELDS]
    rates = np.array([learning_rates[name] for name in FIELDS], np.float64)
    # The bias corrections by step count, looked up: two powers per Gaussian cost more than the rest of its step.
    counts = np.arange(int(steps.max()) + 2 if len(steps) else 1, dtype=np.float64)
    with np.errstate(divide="ignore"):
        inverse_corrections1 = 1.0 / (1.0 - betas[0] ** counts)
        root_corrections2 = 1.0 / np.sqrt(1.0 - betas[1] ** counts)
    _adam(*arrays, steps.numpy(), rates, float(betas[0]), float(betas[1]), float(eps), inverse_corrections1,
          root_corrections2)
    return steps
