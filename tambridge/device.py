"""Which torch device the Gaussian map, the Fusion Bridge and the rendering evaluation run on.

The config's top-level ``device`` is ``cpu`` (the default: the path that ships and is tested), ``cuda`` (or
``cuda:N``) or ``auto``. It is resolved once per run by :func:`resolve_device`; ``cuda`` needs a CUDA build of
torch that sees a GPU and the ``gsplat`` package (the rasteriser's CUDA backend), and ``auto`` takes CUDA only when
both are there. The frontend, the mesh (Open3D) and the exporters run on the CPU whatever the device.
"""

from __future__ import annotations

import torch

from tambridge.errors import ConfigError
from tambridge.gaussians.gsplat_backend import gsplat_available
from tambridge.settings import Device


def resolve_device(requested: Device | str) -> torch.device:
    """The torch device for ``requested`` (``auto``, ``cpu``, ``cuda`` or ``cuda:N``).

    ``auto`` is CUDA when torch sees a GPU and gsplat imports, else the CPU. Raises :class:`ConfigError` naming
    the fix when the value is not one of those, or CUDA is asked for and torch has no GPU or gsplat is missing
    (never a silent fallback to the CPU).
    """
    parsed = Device.parse(requested)
    if parsed is None:
        raise ConfigError(f"device={str(requested)!r}: expected {Device.accepted()}")
    if parsed is Device.auto:
        return resolve_device(Device.cuda) if gsplat_available() else torch.device("cpu")
    if parsed is Device.cpu:
        return torch.device("cpu")
    name = str(parsed)
    if not torch.cuda.is_available():
        build = "a CPU-only build" if torch.version.cuda is None else f"built for CUDA {torch.version.cuda}"
        raise ConfigError(f"device={name!r}: torch {torch.__version__} ({build}) sees no CUDA GPU; run with "
                          f"--device cpu (or --set device=cpu), or on a machine with an NVIDIA GPU install a CUDA "
                          f"build of torch and gsplat (pip install torch gsplat)")
    if not gsplat_available():
        raise ConfigError(f"device={name!r}: the gsplat package is not installed (the CUDA rasteriser); "
                          f"pip install gsplat, or run with --device cpu")
    device = torch.device(name)
    if device.index is not None and device.index >= torch.cuda.device_count():
        raise ConfigError(f"device={name!r}: only {torch.cuda.device_count()} CUDA device(s) here; "
                          f"use cuda:0 .. cuda:{torch.cuda.device_count() - 1}")
    # With its index: tensors report cuda:0, and torch.device("cuda") != torch.device("cuda:0").
    return device if device.index is not None else torch.device("cuda", torch.cuda.current_device())


def device_summary(device: torch.device) -> dict:
    """What metrics.json records about the device that ran: its name, and on CUDA the GPU, the torch, CUDA and
    gsplat versions and the peak GPU memory allocated so far (MB)."""
    summary: dict = {"device": str(device)}
    if device.type == "cuda":
        import gsplat

        summary.update(
            gpu=torch.cuda.get_device_name(device),
            torch_version=torch.__version__,
            cuda_version=torch.version.cuda,
            gsplat_version=getattr(gsplat, "__version__", "unknown"),
            peak_gpu_memory_mb=torch.cuda.max_memory_allocated(device) / 2**20,
        )
    return summary
