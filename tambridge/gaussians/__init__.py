"""Isotropic 3D Gaussians: the model, the differentiable rasteriser (CPU kernel, gsplat, torch reference) and the
online map. Their .ply layout is written and read by :mod:`tambridge.export.splats`."""

from tambridge.gaussians.model import GaussianTensors, RenderOutput, ScreenGaussians
from tambridge.gaussians.rasterizer import render

__all__ = ["GaussianTensors", "RenderOutput", "ScreenGaussians", "render"]
