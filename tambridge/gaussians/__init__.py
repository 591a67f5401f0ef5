"""Isotropic 3D Gaussians: the model, the differentiable rasteriser (CPU kernel, gsplat, torch reference), .ply I/O."""

from tambridge.gaussians.model import GaussianTensors, RenderOutput, ScreenGaussians
from tambridge.gaussians.rasterizer import render

__all__ = ["GaussianTensors", "RenderOutput", "ScreenGaussians", "render"]
