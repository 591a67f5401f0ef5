"""The mapper's Adam step: the numba kernel (:mod:`tambridge.gaussians.adam_kernel`) against its twin, the torch step.

    python benchmarks/adam.py                          # 20k, 60k, 200k Gaussians
    python benchmarks/adam.py --counts 60000 --repeats 100

Each row times one step of :func:`tambridge.gaussians.adam_kernel.adam_step_numba` (the kernel) and of
:func:`tambridge.gaussians.mapper.adam_step_torch` (the twin) on float32 Gaussians, a third of them without a
gradient (outside the step's view), under the thread counts the mapper runs with (``tambridge.threads.TORCH_THREADS``
torch threads, ``mapper.kernel_threads`` numba threads): the median over repeats after warm-up, in milliseconds,
and their ratio. It also gives the largest difference of the parameters after one step from the same state, relative
to the largest change the step made, which the tests bound.

The table goes to stdout, everything to benchmarks/results/adam.json.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402

from benchmarks.kernel_twin import mapper_threads, median_ms, write_result  # noqa: E402
from tambridge.gaussians.adam_kernel import adam_step_numba  # noqa: E402
from tambridge.gaussians.config import MapperConfig  # noqa: E402
from tambridge.gaussians.mapper import ADAM_BETAS, ADAM_EPS, GaussianMap, adam_step_torch  # noqa: E402

SHAPES = {"means_anchor_m": (3,), "rgb": (3,), "log_radii_m": (), "opacity_logits": ()}


def state(count: int, generator: torch.Generator) -> tuple[dict, dict, dict, dict, torch.Tensor]:
    """Parameters, gradients (none for the first third), first and second moments, and step counts of ``count``
    Gaussians, as the mapper holds them."""
    tables = [{name: torch.rand((count,) + shape, generator=generator) for name, shape in SHAPES.items()}
              for _ in range(4)]
    params, grads, exp_avg, exp_avg_sq = tables
    for name in grads:
        grads[name] = grads[name] - 0.5
        grads[name][: count // 3] = 0.0
    exp_avg_sq = {name: value * 1e-2 for name, value in exp_avg_sq.items()}
    return params, grads, exp_avg, exp_avg_sq, torch.randint(1, 200, (count,), generator=generator).float()


def copied(table: dict) -> dict:
    return {name: value.clone() for name, value in table.items()}


def timed_ms(step, count: int, repeats: int, learning_rates: dict) -> float:
    """Median wall milliseconds of one ``step`` on ``count`` Gaussians, each step from the state the last one left."""
    params, grads, exp_avg, exp_avg_sq, steps = state(count, torch.Generator().manual_seed(0))
    counts = [steps]

    def one_step() -> None:
        counts[0] = step(params, grads, exp_avg, exp_avg_sq, counts[0], learning_rates, ADAM_BETAS, ADAM_EPS)

    return median_ms(one_step, repeats)


def measure(count: int, repeats: int) -> dict:
    learning_rates = GaussianMap(MapperConfig()).learning_rates
    params, grads, exp_avg, exp_avg_sq, steps = state(count, torch.Generator().manual_seed(1))
    after = []
    for step in (adam_step_numba, adam_step_torch):
        stepped = copied(params)
        step(stepped, grads, copied(exp_avg), copied(exp_avg_sq), steps, learning_rates, ADAM_BETAS, ADAM_EPS)
        after.append(stepped)
    difference = max(float((after[0][name] - after[1][name]).abs().max()) for name in SHAPES)
    change = max(float((after[1][name] - params[name]).abs().max()) for name in SHAPES)
    kernel_ms = timed_ms(adam_step_numba, count, repeats, learning_rates)
    twin_ms = timed_ms(adam_step_torch, count, repeats, learning_rates)
    return {"gaussians": count, "kernel_ms": kernel_ms, "twin_ms": twin_ms, "twin_over_kernel": twin_ms / kernel_ms,
            "parameter_difference_relative": difference / change}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--counts", nargs="+", type=int, default=[20_000, 60_000, 200_000])
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks" / "results" / "adam.json")
    args = parser.parse_args()
    if any(count <= 0 for count in args.counts):
        raise SystemExit(f"--counts: {args.counts} must all be positive numbers of Gaussians, e.g. 60000")
    with mapper_threads() as threads:
        rows = [measure(count, args.repeats) for count in args.counts]
    print(f"{'Gaussians':>10} {'kernel ms':>10} {'twin ms':>9} {'ratio':>6} {'param diff':>11}")
    for row in rows:
        print(f"{row['gaussians']:10d} {row['kernel_ms']:10.2f} {row['twin_ms']:9.2f} {row['twin_over_kernel']:6.2f} "
              f"{row['parameter_difference_relative']:11.2e}")
    write_result(args.output, threads, args.repeats, rows)


if __name__ == "__main__":
    main()
