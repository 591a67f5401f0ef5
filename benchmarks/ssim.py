"""SSIM in the map loss: the numba kernel (:mod:`tambridge.gaussians.ssim_kernel`) against its twin, pytorch-msssim.

    python benchmarks/ssim.py                          # 160x120, 320x240, 640x480
    python benchmarks/ssim.py --resolutions 640x480 --repeats 50

Each row times one forward and backward pass of :func:`tambridge.gaussians.losses.ssim` (the kernel) and of
:func:`tambridge.gaussians.losses.ssim_reference` (the twin) on a float32 render and frame, under the thread counts
the mapper runs with (``tambridge.threads.TORCH_THREADS`` torch threads, ``mapper.kernel_threads`` numba threads):
the median over repeats after warm-up, in milliseconds, and their ratio. It also gives the largest difference of
the two values and gradients (relative to the largest gradient), which the tests bound.

The table goes to stdout, everything to benchmarks/results/ssim.json.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402

from benchmarks.kernel_twin import mapper_threads, median_ms, write_result  # noqa: E402
from tambridge.gaussians.losses import ssim, ssim_reference  # noqa: E402


def timed_ms(function, rendered: torch.Tensor, observed: torch.Tensor, repeats: int) -> float:
    """Median wall milliseconds of one forward and backward pass of ``function(rendered, observed)``."""
    return median_ms(lambda leaf: function(leaf, observed).backward(), repeats,
                     prepare=lambda: rendered.detach().requires_grad_(True))


def kernel_and_twin(rendered: torch.Tensor, observed: torch.Tensor) -> tuple[list[float], list[torch.Tensor]]:
    """SSIM of ``rendered`` against ``observed`` (H, W, 3) and its gradient to ``rendered``, by the kernel and by the
    twin, in that order."""
    values, grads = [], []
    for function in (ssim, ssim_reference):
        leaf = rendered.clone().requires_grad_(True)
        value = function(leaf, observed)
        value.backward()
        values.append(float(value.detach()))
        grads.append(leaf.grad)
    return values, grads


def measure(width: int, height: int, repeats: int) -> dict:
    generator = torch.Generator().manual_seed(0)
    observed = torch.rand(height, width, 3, generator=generator)
    rendered = (observed + 0.1 * torch.randn(height, width, 3, generator=generator)).clamp(0, 1)
    values, grads = kernel_and_twin(rendered, observed)
    kernel_ms = timed_ms(ssim, rendered, observed, repeats)
    twin_ms = timed_ms(ssim_reference, rendered, observed, repeats)
    return {"resolution": f"{width}x{height}", "kernel_ms": kernel_ms, "twin_ms": twin_ms,
            "twin_over_kernel": twin_ms / kernel_ms, "value_difference": abs(values[0] - values[1]),
            "gradient_difference_relative": float((grads[0] - grads[1]).abs().max() / grads[1].abs().max())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--resolutions", nargs="+", default=["160x120", "320x240", "640x480"])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks" / "results" / "ssim.json")
    args = parser.parse_args()
    sizes = []
    for text in args.resolutions:
        try:
            width, height = (int(part) for part in text.split("x"))
        except ValueError:
            raise SystemExit(f"--resolutions: {text!r} is not WIDTHxHEIGHT, e.g. 640x480") from None
        sizes.append((width, height))
    with mapper_threads() as threads:
        rows = [measure(width, height, args.repeats) for width, height in sizes]
    print(f"{'resolution':>10} {'kernel ms':>10} {'twin ms':>9} {'ratio':>6} {'value diff':>11} {'grad diff':>10}")
    for row in rows:
        print(f"{row['resolution']:>10} {row['kernel_ms']:10.2f} {row['twin_ms']:9.2f} {row['twin_over_kernel']:6.2f} "
              f"{row['value_difference']:11.2e} {row['gradient_difference_relative']:10.2e}")
    write_result(args.output, threads, args.repeats, rows)


if __name__ == "__main__":
    main()
