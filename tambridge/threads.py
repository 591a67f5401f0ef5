"""Thread counts of torch and numba around compute-heavy blocks."""

from __future__ import annotations

import contextlib
from typing import Iterator

import numba
import torch


TORCH_THREADS = 1
"""torch intra-op threads while mapping. The mapper's torch ops are small (one view's Gaussians) and torch's
OpenMP pool fights the rasteriser's numba OpenMP threads for the cores."""


@contextlib.contextmanager
def compute_threads(torch_count: int, numba_count: int) -> Iterator[None]:
    """Run a block with ``torch_count`` torch intra-op threads and ``numba_count`` numba threads (0: numba's
    default, all cores; no more than numba's pool has, which is one on a one-core machine), then restore the
    previous counts."""
    previous = torch.get_num_threads(), numba.get_num_threads()
    torch.set_num_threads(torch_count)
    pool = numba.config.NUMBA_NUM_THREADS
    numba.set_num_threads(min(numba_count, pool) if numba_count > 0 else pool)
    try:
        yield
    finally:
        torch.set_num_threads(previous[0])
        numba.set_num_threads(previous[1])
