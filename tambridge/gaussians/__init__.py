"""Isotropic 3D Gaussians: the model, the differentiable rasteriser (CPU kernel, gsplat, torch reference), .ply I/O."""

from tambridge.gaussians.model import GaussianTensors, RenderOutput, ScreenGaussians
from tambridge.gaussians.ply import load_ply, save_ply
from tambridge.gaussians.rasterizer import render

__all__ = ["GaussianTensors", "RenderOutput", "ScreenGaussians", "load_ply", "render", "save_ply"]
