"""Gaussian splats as .ply in the INRIA 3DGS layout, which SuperSplat, gsplat's viewer and SIBR read.

One ``vertex`` element, binary little endian, float32 properties in this order:
``x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3``, where

- ``f_dc = (rgb - 0.5) / C0`` is the degree-0 spherical-harmonic coefficient of the colour (``C0 = 1 / (2 sqrt(pi))``);
- ``opacity`` is the logit of the opacity, ``scale_k`` the log of the radius in metres (isotropic: the same three
  times) and ``rot`` the identity quaternion, w first; the normals are zero (3DGS writes them so).

Files from other 3DGS trainers load too: ``f_rest_*`` (higher SH degrees) are ignored, an anisotropic Gaussian
becomes isotropic with the mean of its three radii, colours are clipped to [0, 1].
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from tambridge.errors import SplatFormatError
from tambridge.files import atomic_path
from tambridge.gaussians.model import GaussianTensors

SH_C0 = 0.28209479177387814
"""Degree-0 spherical-harmonic basis constant, 1 / (2 sqrt(pi))."""

PROPERTIES = (
    "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2",
    "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
)  # fmt: skip
"""The vertex properties written, in file order, all float32."""


def save_ply(path: Path, gaussians: GaussianTensors) -> None:
    """Write ``gaussians`` to ``path`` (atomically) in the INRIA 3DGS layout."""
    count = len(gaussians)
    columns = {
        name: tensor.detach().to("cpu", torch.float32).numpy()
        for name, tensor in (
            ("means", gaussians.means_m),
            ("f_dc", (gaussians.rgb - 0.5) / SH_C0),
            ("opacity", gaussians.opacity_logits),
            ("log_radius", gaussians.log_radii_m),
        )
    }
    vertices = np.zeros(count, dtype=[(name, "<f4") for name in PROPERTIES])
    for axis, name in enumerate("xyz"):
        vertices[name] = columns["means"][:, axis]
    for channel in range(3):
        vertices[f"f_dc_{channel}"] = columns["f_dc"][:, channel]
        vertices[f"scale_{channel}"] = columns["log_radius"]
    vertices["opacity"] = columns["opacity"]
    vertices["rot_0"] = 1.0
    with atomic_path(Path(path)) as temp_path:
        PlyData([PlyElement.describe(vertices, "vertex")], byte_order="<").write(str(temp_path))


def load_ply(path: Path, device: str | torch.device = "cpu") -> GaussianTensors:
    """Read a 3DGS .ply (ours or any INRIA-layout file) into float32 tensors on ``device``."""
    path = Path(path)
    if not path.is_file():
        raise SplatFormatError(f"{path}: not found; pass a .ply written by tambridge or a 3DGS trainer")
    try:
        ply = PlyData.read(str(path))
    except Exception as error:  # plyfile raises several types on malformed input
        raise SplatFormatError(f"{path}: not a readable .ply file ({error})") from error
    if "vertex" not in [element.name for element in ply.elements]:
        raise SplatFormatError(f"{path}: no 'vertex' element; a 3DGS .ply stores one vertex per Gaussian")
    vertices = ply["vertex"].data
    required = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2")
    missing = [name for name in required if name not in vertices.dtype.names]
    if missing:
        raise SplatFormatError(
            f"{path}: vertex lacks {', '.join(missing)}; expected the INRIA 3DGS layout ({' '.join(PROPERTIES)})"
        )

    def stacked(names: tuple[str, ...]) -> np.ndarray:
        return np.stack([np.asarray(vertices[name], dtype=np.float64) for name in names], axis=1)

    rgb = np.clip(stacked(("f_dc_0", "f_dc_1", "f_dc_2")) * SH_C0 + 0.5, 0.0, 1.0)
    log_radii = np.log(np.exp(stacked(("scale_0", "scale_1", "scale_2"))).mean(axis=1))
    arrays = (stacked(("x", "y", "z")), rgb, log_radii, np.asarray(vertices["opacity"], dtype=np.float64))
    means, rgb, log_radii, opacity_logits = (torch.tensor(array, dtype=torch.float32, device=device) for array in arrays)
    return GaussianTensors(means_m=means, rgb=rgb, log_radii_m=log_radii, opacity_logits=opacity_logits)
