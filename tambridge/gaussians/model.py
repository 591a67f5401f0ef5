"""What the rasteriser takes and gives: isotropic Gaussians, their screen-space projection, the rendered maps.

The image model (TAMBRIDGE paper, Sec. 3.4, SplaTAM's isotropic Gaussians, but with 3DGS's EWA footprint instead of
the paper's circle of radius ``f r / d``, so that a 3DGS viewer shows splats.ply as the rasteriser renders it):

- a Gaussian ``i`` has a mean ``mu_i`` (world, metres), an RGB colour ``c_i`` in [0, 1], an isotropic radius
  ``r_i`` (metres, stored as its log) and an opacity ``o_i = sigmoid(opacity_logit_i)``;
- it projects to the pixel ``mu2D_i = K mu_cam_i / d_i``, where ``d_i`` is the camera-frame depth z of its mean,
  with the EWA 2D covariance ``Sigma2D_i = J_i (r_i^2 I) J_i^T``, ``J_i = [[fx/d, 0, -fx xn/d], [0, fy/d, -fy yn/d]]``
  the Jacobian of the projection at the mean (``xn = x / d``, ``yn = y / d``), i.e.
  ``Sigma2D = (r/d)^2 [[fx^2 (1 + xn^2), fx fy xn yn], [fx fy xn yn, fy^2 (1 + yn^2)]]``: what 3DGS, gsplat and the
  web viewers draw. As gsplat (and INRIA's 3DGS) do, ``xn``, ``yn`` in J are clamped to the image's edge plus 0.3 of
  the half field of view (:func:`jacobian_limits`), which bounds a splat's elongation; no ``eps2d`` dilation is
  added (antimatter15's viewer adds none, gsplat is called with ``eps2d=0``);
- at a pixel ``p`` (pixel centres at integer coordinates, OpenCV convention) it has the weight
  ``alpha_i(p) = min(ALPHA_MAX, o_i exp(-d^T Q_i d / 2))``, ``d = p - mu2D_i``, ``Q_i = Sigma2D_i^-1`` (the *conic*),
  and 0 where ``d^T Q_i d > SIGMA_CUTOFF^2``;
- Gaussians are composited front to back by ``d_i`` (rounded to float32, ties in index order): with
  ``T_i = prod_{j<i} (1 - alpha_j)``,
  ``C(p) = sum_i c_i alpha_i T_i + T_final * background``, ``D(p) = sum_i d_i alpha_i T_i`` and the silhouette
  (border mask) ``M_b(p) = sum_i alpha_i T_i = 1 - T_final``;
- compositing stops before the first Gaussian that would bring the transmittance below ``TRANSMITTANCE_MIN``
  (that Gaussian and all behind it are left out, exactly as 3DGS does), and Gaussians with ``d_i <= NEAR_PLANE_M``
  are skipped.

``D`` is *not* normalised by the silhouette (as in SplaTAM): where ``M_b < 1`` it is smaller than the surface
depth; divide by ``silhouette`` where a normalised depth is wanted.
"""

from __future__ import annotations

import dataclasses

import torch

from tambridge.camera import Camera
from tambridge.geometry import exp_se3_torch

NEAR_PLANE_M = 0.01
"""Gaussians whose camera-frame depth is at most this are not rendered."""
SIGMA_CUTOFF = 3.0
"""A Gaussian touches only the pixels within this many standard deviations (Mahalanobis distance in its 2D
covariance) of its projected mean."""
JACOBIAN_SLACK = 0.3
"""The EWA Jacobian is evaluated at most this fraction of the half field of view beyond the image's edge (gsplat's
and 3DGS's clamp)."""
ALPHA_MAX = 0.99
"""Per-Gaussian alpha is clamped here (3DGS), which keeps ``1 / (1 - alpha)`` finite in the backward pass."""
TRANSMITTANCE_MIN = 1e-4
"""Compositing stops before a Gaussian that would bring the transmittance below this."""


FIELDS = ("means_anchor_m", "rgb", "log_radii_m", "opacity_logits")
"""The fields :class:`tambridge.gaussians.mapper.GaussianMap` stores and optimises per Gaussian (the mean in its
anchor view's camera frame), in the order its Adam kernel takes them."""


@dataclasses.dataclass
class GaussianTensors:
    """Activated parameters of N isotropic Gaussians, all torch tensors on one device and of one float dtype.

    means_m: (N, 3) world-frame means, metres. rgb: (N, 3) colours in [0, 1]. log_radii_m: (N,) natural log
    of the radius in metres. opacity_logits: (N,) logits of the opacity (opacity = sigmoid(logit)).
    """

    means_m: torch.Tensor
    rgb: torch.Tensor
    log_radii_m: torch.Tensor
    opacity_logits: torch.Tensor

    def __post_init__(self) -> None:
        count = self.means_m.shape[0]
        assert self.means_m.shape == (count, 3), self.means_m.shape
        assert self.rgb.shape == (count, 3), self.rgb.shape
        assert self.log_radii_m.shape == (count,), self.log_radii_m.shape
        assert self.opacity_logits.shape == (count,), self.opacity_logits.shape

    def __len__(self) -> int:
        return self.means_m.shape[0]


@dataclasses.dataclass
class ScreenGaussians:
    """Gaussians projected into one camera, differentiable w.r.t. the GaussianTensors and the pose.

    means_px: (N, 2) projected means (u, v), pixels. conics_px: (N, 3) entries (a, b, c) of the inverse 2D
    covariance ``[[a, b], [b, c]]``, px^-2. bounds_px: (N,) ``SIGMA_CUTOFF`` standard deviations along the largest
    axis, pixels: the radius of the circle around the mean that holds the footprint (not differentiable; a box for
    culling and binning). depths_m: (N,) camera-frame z, metres (<= NEAR_PLANE_M for Gaussians to skip; their other
    fields are finite but meaningless). opacity: (N,) in (0, 1). rgb: (N, 3).
    """

    means_px: torch.Tensor
    conics_px: torch.Tensor
    bounds_px: torch.Tensor
    depths_m: torch.Tensor
    opacity: torch.Tensor
    rgb: torch.Tensor


@dataclasses.dataclass
class RenderOutput:
    """Rendered maps of one view. rgb: (H, W, 3). depth_m: (H, W), unnormalised (see module doc). silhouette: (H, W) in [0, 1]."""

    rgb: torch.Tensor
    depth_m: torch.Tensor
    silhouette: torch.Tensor


def camera_from_world_tensor(world_from_camera: torch.Tensor, pose_delta: torch.Tensor | None) -> torch.Tensor:
    """(4, 4) float64 ``camera_from_world`` of ``world_from_camera @ exp_se3(pose_delta)``.

    ``pose_delta`` (6,) is a right perturbation ``(rho, phi)`` in the camera frame; gradients flow to it.
    """
    world_from_camera = torch.as_tensor(world_from_camera).to(torch.float64)
    assert world_from_camera.shape == (4, 4), world_from_camera.shape
    if pose_delta is not None:
        assert pose_delta.shape == (6,), pose_delta.shape
        world_from_camera = world_from_camera.to(pose_delta.device) @ exp_se3_torch(pose_delta.to(torch.float64))
    rotation_t = world_from_camera[:3, :3].T
    top = torch.cat([rotation_t, -(rotation_t @ world_from_camera[:3, 3:4])], dim=1)
    bottom = torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64, device=top.device)
    return torch.cat([top, bottom], dim=0)


def camera_frame_means(
    gaussians: GaussianTensors, world_from_camera: torch.Tensor, pose_delta: torch.Tensor | None = None
) -> torch.Tensor:
    """(N, 3) means in the camera frame of ``world_from_camera @ exp_se3(pose_delta)``, dtype of the means.

    Element by element in a fixed order, ((x r0 + y r1) + z r2) + t, as :func:`cpu_kernel.project` computes it: a
    matmul's rounding depends on the BLAS kernel (MKL fuses multiply-adds on AVX-512 machines), and the forward-only
    path must give the same depths, bit for bit, or ties in the front-to-back order break differently.
    """
    camera_from_world = camera_from_world_tensor(world_from_camera, pose_delta).to(gaussians.means_m)
    x, y, z = gaussians.means_m.unbind(1)
    rotation, translation = camera_from_world[:3, :3], camera_from_world[:3, 3]
    return torch.stack([((x * rotation[row, 0] + y * rotation[row, 1]) + z * rotation[row, 2]) + translation[row]
                        for row in range(3)], dim=1)


def jacobian_limits(camera: Camera) -> tuple[float, float, float, float]:
    """Bounds (x_lo, x_hi, y_lo, y_hi) on ``x / z`` and ``y / z`` where the EWA Jacobian is evaluated: the image's
    edge (pixel edges at -0.5 and width - 0.5) plus ``JACOBIAN_SLACK`` of the half field of view, as gsplat does."""
    slack_x = JACOBIAN_SLACK * 0.5 * camera.width / camera.fx
    slack_y = JACOBIAN_SLACK * 0.5 * camera.height / camera.fy
    return (
        -(camera.cx + 0.5) / camera.fx - slack_x, (camera.width - 0.5 - camera.cx) / camera.fx + slack_x,
        -(camera.cy + 0.5) / camera.fy - slack_y, (camera.height - 0.5 - camera.cy) / camera.fy + slack_y,
    )  # fmt: skip


def ewa_terms(xn, yn, radius_over_depth):
    """The terms of ``Sigma2D``'s inverse (module doc) of an isotropic Gaussian: ``(1 + yn^2, xn yn, 1 + xn^2, w)``
    with ``w = (r / z)^2 (1 + xn^2 + yn^2)``, so that the conic is ``a = (1 + yn^2) / (w fx^2)``,
    ``b = -xn yn / (w fx fy)``, ``c = (1 + xn^2) / (w fy^2)`` (px^-2), and the largest eigenvalue of ``Sigma2D`` is
    at most ``max(fx, fy)^2 w`` (px^2; equal to it when fx == fy).

    xn, yn: the (clamped) normalised coordinates ``x / z``, ``y / z`` of its mean; radius_over_depth: ``r / z``.
    Plain arithmetic, so that torch tensors (differentiably) and numba scalars (the CPU kernel's projection) run the
    same expressions.
    """
    xx, yy = xn * xn, yn * yn
    plus_xx = 1.0 + xx
    return 1.0 + yy, xn * yn, plus_xx, radius_over_depth * radius_over_depth * (plus_xx + yy)


def conic_scales(camera: Camera) -> tuple[float, float, float]:
    """What :func:`ewa_terms`' first three terms are multiplied by (after division by ``w``) to give the conic."""
    return 1.0 / (camera.fx * camera.fx), -1.0 / (camera.fx * camera.fy), 1.0 / (camera.fy * camera.fy)


def project_to_screen(gaussians: GaussianTensors, means_cam_m: torch.Tensor, camera: Camera) -> ScreenGaussians:
    """Project camera-frame means ``(N, 3)`` and radii to pixels: ``mu2D = K mu_cam / d`` and the EWA footprint
    (module doc), differentiable w.r.t. the means and radii."""
    depths = means_cam_m[:, 2]
    # Behind-the-near-plane Gaussians get a stand-in depth of 1 so that nothing here is inf or NaN (a NaN
    # would leak into the gradients through the chain rule even though the rasteriser skips them).
    safe_depths = torch.where(depths > NEAR_PLANE_M, depths, torch.ones_like(depths))
    x_lo, x_hi, y_lo, y_hi = jacobian_limits(camera)
    xn = torch.clamp(means_cam_m[:, 0] / safe_depths, x_lo, x_hi)
    yn = torch.clamp(means_cam_m[:, 1] / safe_depths, y_lo, y_hi)
    radius_over_depth = torch.exp(gaussians.log_radii_m) / safe_depths
    plus_yy, xy, plus_xx, spread = ewa_terms(xn, yn, radius_over_depth)
    scales = torch.tensor(conic_scales(camera), dtype=spread.dtype, device=spread.device)
    return ScreenGaussians(
        means_px=camera.project_torch(means_cam_m, safe_depths),
        # (N, 3) at once: fewer elementwise ops (and backward nodes) than three columns
        conics_px=torch.stack([plus_yy, xy, plus_xx], dim=1) * (scales / spread[:, None]),
        bounds_px=(SIGMA_CUTOFF * max(camera.fx, camera.fy)) * torch.sqrt(spread.detach()),
        depths_m=depths,
        opacity=torch.sigmoid(gaussians.opacity_logits),
        rgb=gaussians.rgb,
    )
