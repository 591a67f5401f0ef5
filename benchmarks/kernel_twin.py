"""What the kernel-against-twin benchmarks (``ssim.py``, ``adam.py``) share: the median time of a call under the
mapper's thread counts, and the JSON they write."""

from __future__ import annotations

import contextlib
import datetime
import json
import statistics
import time
from pathlib import Path
from typing import Callable, Iterator

from benchmarks.machine import describe_machine
from tambridge.gaussians.config import MapperConfig
from tambridge.threads import TORCH_THREADS, compute_threads

WARM_UPS = 2
"""Calls before the timed ones: numba's compilation or cache load, torch's first allocation."""


def median_ms(call: Callable, repeats: int, prepare: Callable[[], object] | None = None) -> float:
    """Median wall milliseconds of ``call(prepare())`` (``call()`` without ``prepare``) over ``repeats`` calls after
    :data:`WARM_UPS`; ``prepare`` runs outside the timing."""
    times = []
    for attempt in range(repeats + WARM_UPS):
        argument = () if prepare is None else (prepare(),)
        start = time.perf_counter()
        call(*argument)
        if attempt >= WARM_UPS:
            times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


@contextlib.contextmanager
def mapper_threads() -> Iterator[int]:
    """The thread counts the mapper runs with (``TORCH_THREADS`` torch threads, ``mapper.kernel_threads`` numba
    threads) for the block; yields the numba count."""
    threads = MapperConfig().kernel_threads
    with compute_threads(TORCH_THREADS, threads):
        yield threads


def write_result(output: Path, numba_threads: int, repeats: int, rows: list[dict]) -> None:
    """The benchmark's JSON: date, machine, thread counts, repeats and its rows."""
    result = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
              "machine": describe_machine(), "torch_threads": TORCH_THREADS, "numba_threads": numba_threads,
              "repeats": repeats, "rows": rows}
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text(json.dumps(result, indent=1) + "\n")
