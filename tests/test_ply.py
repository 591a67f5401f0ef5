"""INRIA 3DGS .ply export and import: round trip, header layout, foreign files, errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from tambridge.errors import SplatFormatError
from tambridge.gaussians import GaussianTensors
from tambridge.export.splats import SH_C0, load_ply, save_ply

# The INRIA layout as the issue specifies it, written out by hand (not imported) so the test checks the code.
EXPECTED_PROPERTIES = [
    "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2",
    "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
]  # fmt: skip


def some_gaussians(count: int = 257) -> GaussianTensors:
    generator = torch.Generator().manual_seed(0)
    return GaussianTensors(
        means_m=torch.randn(count, 3, generator=generator) * 3.0,
        rgb=torch.rand(count, 3, generator=generator),
        log_radii_m=torch.rand(count, generator=generator) * 4.0 - 6.0,
        opacity_logits=torch.randn(count, generator=generator) * 3.0,
    )


def test_round_trip(tmp_path):
    gaussians = some_gaussians()
    save_ply(tmp_path / "splats.ply", gaussians)
    loaded = load_ply(tmp_path / "splats.ply")
    for name in ("means_m", "rgb", "log_radii_m", "opacity_logits"):
        torch.testing.assert_close(getattr(loaded, name), getattr(gaussians, name), atol=2e-6, rtol=1e-6)
    assert [path.name for path in tmp_path.iterdir()] == ["splats.ply"]  # no temporary left behind


def test_header_and_values_follow_inria_layout(tmp_path):
    gaussians = some_gaussians(5)
    save_ply(tmp_path / "splats.ply", gaussians)
    raw = (tmp_path / "splats.ply").read_bytes()
    header, body = raw.split(b"end_header\n", 1)
    lines = header.decode("ascii").splitlines()
    assert lines[0] == "ply"
    assert lines[1] == "format binary_little_endian 1.0"
    assert lines[2] == "element vertex 5"
    properties = [line for line in lines if line.startswith("property")]
    assert len(properties) == len(EXPECTED_PROPERTIES)
    for line, name in zip(properties, EXPECTED_PROPERTIES):
        assert line == f"property float {name}"
    assert len(body) == 5 * len(EXPECTED_PROPERTIES) * 4
    values = np.frombuffer(body, dtype="<f4").reshape(5, len(EXPECTED_PROPERTIES))
    column = {name: values[:, index] for index, name in enumerate(EXPECTED_PROPERTIES)}
    np.testing.assert_allclose(np.stack([column[a] for a in "xyz"], 1), gaussians.means_m.numpy(), rtol=1e-7)
    np.testing.assert_array_equal(np.stack([column[f"n{a}"] for a in "xyz"], 1), 0.0)
    f_dc = np.stack([column[f"f_dc_{k}"] for k in range(3)], 1)
    np.testing.assert_allclose(f_dc, (gaussians.rgb.numpy() - 0.5) / 0.28209479177387814, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(column["opacity"], gaussians.opacity_logits.numpy(), rtol=1e-7)
    for k in range(3):
        np.testing.assert_allclose(column[f"scale_{k}"], gaussians.log_radii_m.numpy(), rtol=1e-7)
    np.testing.assert_array_equal(np.stack([column[f"rot_{k}"] for k in range(4)], 1), [[1.0, 0.0, 0.0, 0.0]] * 5)


def test_loads_full_inria_file_with_sh_rest_and_anisotropic_scales(tmp_path):
    """A file as the 3DGS trainer writes it (degree-3 SH, 62 properties, anisotropic, rotated)."""
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{k}" for k in range(45)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    vertices = np.zeros(2, dtype=[(name, "<f4") for name in names])
    vertices["x"], vertices["y"], vertices["z"] = [1.0, -1.0], [2.0, 0.5], [3.0, 4.0]
    vertices["f_dc_0"], vertices["f_dc_1"], vertices["f_dc_2"] = [0.0, 10.0], [1.0, -10.0], [-1.0, 0.2]
    for k in range(45):
        vertices[f"f_rest_{k}"] = 0.3
    vertices["opacity"] = [0.5, -2.0]
    vertices["scale_0"], vertices["scale_1"], vertices["scale_2"] = np.log([[0.01, 0.1], [0.02, 0.1], [0.03, 0.1]])
    vertices["rot_0"], vertices["rot_2"] = 0.6, 0.8
    PlyData([PlyElement.describe(vertices, "vertex")]).write(str(tmp_path / "trained.ply"))
    loaded = load_ply(tmp_path / "trained.ply")
    torch.testing.assert_close(loaded.means_m, torch.tensor([[1.0, 2.0, 3.0], [-1.0, 0.5, 4.0]]))
    expected_rgb = [[0.5, 0.5 + SH_C0, 0.5 - SH_C0], [1.0, 0.0, 0.5 + 0.2 * SH_C0]]  # out-of-range colours clipped
    torch.testing.assert_close(loaded.rgb, torch.tensor(expected_rgb), atol=1e-6, rtol=0)
    torch.testing.assert_close(loaded.log_radii_m, torch.log(torch.tensor([0.02, 0.1])), atol=1e-6, rtol=0)
    torch.testing.assert_close(loaded.opacity_logits, torch.tensor([0.5, -2.0]))


def test_file_without_gaussian_properties_is_rejected(tmp_path):
    vertices = np.zeros(3, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    PlyData([PlyElement.describe(vertices, "vertex")]).write(str(tmp_path / "points.ply"))
    with pytest.raises(SplatFormatError, match="points.ply: vertex lacks f_dc_0"):
        load_ply(tmp_path / "points.ply")
    with pytest.raises(SplatFormatError, match="not found"):
        load_ply(tmp_path / "missing.ply")
