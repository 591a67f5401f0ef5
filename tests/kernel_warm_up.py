"""Compile numba's kernels into its on-disk cache as the test suite uses them: a short demo run with Open3D's
frontend (the bridge and the map, in float32), float64 renders and SSIM with their gradients (the kernels' tests check
those against their twins and finite differences), and the demo run with ORB's frontend. conftest runs this in a
second process while the first tests run."""

import sys
from pathlib import Path

import numpy as np
import torch

from cli import main as cli
from tambridge.gaussians.losses import ssim
from tambridge.geometry import look_at
from tests.numba_cache_lock import serialise_numba_cache_saves
from tests.test_rasterizer import camera_of, random_gaussians, requiring_grad, scalar_loss
from tests.test_ssim_kernel import image_pair


def main(folder: Path) -> None:
    """A demo run into ``folder`` with Open3D's frontend, float64 renders (with and without a pose twist) and SSIM
    with gradients, then the demo run with ORB's frontend."""
    serialise_numba_cache_saves()
    # The map's kernels first, behind Open3D's frontend: the first quick test that tracks compiles ORB's meanwhile.
    demo = ["demo", "--frames", "20", "--size", "160x120"]
    cli([*demo, "-o", str(folder / "open3d"), "--set", "frontend.kind=open3d"], standalone_mode=False)
    camera = camera_of(24, 18)
    world_from_camera = look_at(np.array([0.05, 0.1, -0.1]), np.array([0.0, 0.0, 2.0]), up=np.array([0.0, -1.0, 0.0]))
    gaussians = requiring_grad(random_gaussians(40, seed=7, dtype=torch.float64, radius_m=(0.05, 0.15)))
    for pose_delta in (None, torch.zeros(6, dtype=torch.float64, requires_grad=True)):
        scalar_loss(gaussians, camera, world_from_camera, pose_delta, "cpu").backward()
    rendered, observed = image_pair(30, 40, torch.float64)
    ssim(rendered.requires_grad_(True), observed).backward()
    cli([*demo, "-o", str(folder / "demo")], standalone_mode=False)


if __name__ == "__main__":
    main(Path(sys.argv[1]))
