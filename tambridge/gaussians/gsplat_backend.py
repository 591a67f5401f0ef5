"""CUDA rendering through gsplat (only when a GPU and the ``gsplat`` package are present; never needed on CPU).

The Gaussians are handed over already in the camera frame (identity view matrix), so the pose chain,
``pose_delta`` included, stays in torch and its gradients flow exactly as on the CPU path.

Our image model (:mod:`tambridge.gaussians.model`) is gsplat's: the isotropic 3D covariance ``r^2 I`` projected
with the EWA Jacobian (clamped as gsplat clamps it), no ``eps2d`` dilation (we pass ``eps2d=0``; gsplat's default
adds 0.3 px^2 of blur to every 2D covariance), alpha clamped at 0.99. What still differs, documented rather than hidden:

- gsplat skips alphas below 1/255 and cuts splats at 3 sigma of the largest eigenvalue (a square tile box);
  we cut at 3 sigma per pixel in the Mahalanobis sense. The colour differences are at the 1/255 level.
- Depth: we ask for ``render_mode="RGB+D"``, gsplat's *accumulated* depth ``sum_i z_i alpha_i T_i``, which is our
  unnormalised ``D(p)``; gsplat's "ED" (expected depth) would be ``D / silhouette``.
- Pixel centres: gsplat puts pixel ``i``'s centre at ``i + 0.5``, OpenCV (ours) at ``i``, so cx, cy move by 0.5.
"""

from __future__ import annotations

import importlib.util

import torch

from tambridge.camera import Camera
from tambridge.gaussians.model import NEAR_PLANE_M, GaussianTensors, RenderOutput


def gsplat_available() -> bool:
    """True when CUDA is usable and gsplat can be imported."""
    return torch.cuda.is_available() and importlib.util.find_spec("gsplat") is not None


def render_gsplat(
    gaussians: GaussianTensors, means_cam_m: torch.Tensor, camera: Camera, background_rgb: torch.Tensor
) -> RenderOutput:
    """Render camera-frame means ``(N, 3)`` with the other fields of ``gaussians`` on their (CUDA) device."""
    import gsplat

    device, dtype = means_cam_m.device, means_cam_m.dtype
    count = means_cam_m.shape[0]
    K = torch.tensor(
        [[camera.fx, 0.0, camera.cx + 0.5], [0.0, camera.fy, camera.cy + 0.5], [0.0, 0.0, 1.0]], dtype=dtype, device=device
    )
    quats = torch.zeros(count, 4, dtype=dtype, device=device)
    quats[:, 0] = 1.0  # identity rotation, w first
    colours, alphas, _ = gsplat.rasterization(
        means=means_cam_m,
        quats=quats,
        scales=torch.exp(gaussians.log_radii_m)[:, None].repeat(1, 3),
        opacities=torch.sigmoid(gaussians.opacity_logits),
        colors=gaussians.rgb,
        viewmats=torch.eye(4, dtype=dtype, device=device)[None],
        Ks=K[None],
        width=camera.width,
        height=camera.height,
        near_plane=NEAR_PLANE_M,
        eps2d=0.0,
        backgrounds=background_rgb.to(device=device, dtype=dtype)[None],  # gsplat appends the depth channel's 0
        render_mode="RGB+D",
    )
    return RenderOutput(rgb=colours[0, :, :, :3], depth_m=colours[0, :, :, 3], silhouette=alphas[0, :, :, 0])
