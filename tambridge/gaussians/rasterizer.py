"""Differentiable rendering of isotropic Gaussians (EWA footprints, :mod:`tambridge.gaussians.model`): colour, depth and silhouette, with gradients to the pose.

``render`` moves the means into the camera frame of ``world_from_camera @ exp_se3(pose_delta)`` and projects
them in torch (so autograd carries the pose and projection chain), then composites with one of three backends:

- ``"cpu"``: the numba tile kernels of :mod:`tambridge.gaussians.cpu_kernel` behind a ``torch.autograd.Function``
  (the path that ships; exact forward and backward of the image model in :mod:`tambridge.gaussians.model`). With
  no ``pose_delta`` (the mapper's steps) the projection and its backward run in numba as well
  (:class:`_CpuProject`; the torch projection is its twin, kept for renders whose pose is optimised). When
  autograd records nothing (``torch.no_grad()`` or no input requiring gradients: evaluation, viewer, meshing) the
  projection runs in numba too and nothing is kept for a backward pass (:func:`render_cpu_untracked`);
- ``"gsplat"``: gsplat's CUDA rasteriser (:mod:`tambridge.gaussians.gsplat_backend`);
- ``"reference"``: the dense torch twin (:mod:`tambridge.gaussians.reference`), for tests.

``"auto"`` takes gsplat when the Gaussians are on a CUDA device and gsplat imports, else the CPU kernel.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np
import torch
from torch.autograd.function import once_differentiable

from tambridge.camera import Camera
from tambridge.gaussians import cpu_kernel
from tambridge.gaussians.gsplat_backend import gsplat_available, render_gsplat
from tambridge.gaussians.model import (
    GaussianTensors,
    RenderOutput,
    ScreenGaussians,
    camera_frame_means,
    camera_from_world_tensor,
    project_to_screen,
)
from tambridge.gaussians.reference import composite_reference

BACKENDS = ("auto", "cpu", "reference", "gsplat")


def render(
    gaussians: GaussianTensors,
    camera: Camera,
    world_from_camera: torch.Tensor | np.ndarray,
    pose_delta: torch.Tensor | None = None,
    background_rgb: Sequence[float] = (0.0, 0.0, 0.0),
    backend: str = "auto",
) -> RenderOutput:
    """Render ``gaussians`` seen by ``camera`` at ``world_from_camera @ exp_se3(pose_delta)``.

    camera: pinhole intrinsics of the rendered image (its distortion is ignored: frames are undistorted by the reader).
    world_from_camera: (4, 4) pose (float64 preferred). pose_delta: (6,) twist ``(rho, phi)`` applied on the right,
    in the camera frame, or None. background_rgb: colour behind the Gaussians. Returns rgb (H, W, 3), depth_m (H, W)
    (unnormalised, see :mod:`tambridge.gaussians.model`) and silhouette (H, W), in the Gaussians' dtype and device;
    all are differentiable w.r.t. every field of ``gaussians`` and ``pose_delta``.
    """
    if backend not in BACKENDS:
        raise ValueError(f"render: backend {backend!r} is not one of {', '.join(BACKENDS)}")
    device = gaussians.means_m.device
    if backend == "auto":
        backend = "gsplat" if device.type == "cuda" and gsplat_available() else "cpu"
    if backend == "gsplat" and not gsplat_available():
        raise RuntimeError("render: backend 'gsplat' needs a CUDA device and the gsplat package; use backend='cpu'")
    if isinstance(world_from_camera, np.ndarray):
        world_from_camera = torch.from_numpy(world_from_camera)
    if backend == "cpu" and not _tracks_gradients(gaussians, pose_delta):
        camera_from_world = camera_from_world_tensor(world_from_camera, pose_delta)
        return render_cpu_untracked(gaussians, camera, camera_from_world, background_rgb)
    if backend == "cpu" and pose_delta is None:
        packed = _CpuProject.apply(gaussians.means_m, gaussians.log_radii_m, gaussians.opacity_logits, gaussians.rgb,
                                   camera_from_world_tensor(world_from_camera, None), camera)
        return composite_packed(packed, camera.width, camera.height,
                                torch.tensor(background_rgb, dtype=packed.dtype, device=device))
    means_cam_m = camera_frame_means(gaussians, world_from_camera.to(device), pose_delta)
    background = torch.tensor(background_rgb, dtype=means_cam_m.dtype, device=device)
    if backend == "gsplat":
        return render_gsplat(gaussians, means_cam_m, camera, background)
    screen = project_to_screen(gaussians, means_cam_m, camera)
    if backend == "reference":
        return composite_reference(screen, camera.width, camera.height, background)
    return composite_cpu(screen, camera.width, camera.height, background)


def _tracks_gradients(gaussians: GaussianTensors, pose_delta: torch.Tensor | None) -> bool:
    """Whether autograd records a render of ``gaussians`` at ``pose_delta``."""
    tensors = [getattr(gaussians, field.name) for field in dataclasses.fields(gaussians)]
    tensors += [pose_delta] if pose_delta is not None else []
    return torch.is_grad_enabled() and any(tensor.requires_grad for tensor in tensors)


def render_cpu_untracked(
    gaussians: GaussianTensors, camera: Camera, camera_from_world: torch.Tensor, background_rgb: Sequence[float]
) -> RenderOutput:
    """The CPU kernel's render when nothing needs gradients (evaluation, viewer, meshing): what ``render`` gives,
    with the projection done in one numba pass (:func:`cpu_kernel.project`) instead of torch and no autograd state.

    camera_from_world: (4, 4) float64. Outputs in the Gaussians' dtype and device, not differentiable.
    """
    dtype = gaussians.means_m.dtype
    _, arrays = _projection_arrays(gaussians.means_m, gaussians.log_radii_m, gaussians.opacity_logits, gaussians.rgb)
    packed = cpu_kernel.project(*arrays, camera_from_world.detach().cpu().numpy(), camera)
    bins = cpu_kernel.bin_tiles(packed, camera.width, camera.height, with_slots=False)
    background = np.asarray(background_rgb, np.float64)
    maps = cpu_kernel.composite_forward(bins, camera.width, camera.height, background, packed.dtype)[:3]
    device = gaussians.means_m.device
    return RenderOutput(*(torch.from_numpy(image).to(device=device, dtype=dtype) for image in maps))


def _projection_arrays(means_m, log_radii_m, opacity_logits, rgb) -> tuple[torch.dtype, list[np.ndarray]]:
    """The fields :func:`cpu_kernel.project` reads, as contiguous CPU arrays, and the dtype they are in: float64
    Gaussians are projected in float64, float32 (and others) in float32, as torch projects them."""
    storage = torch.float64 if means_m.dtype == torch.float64 else torch.float32
    return storage, [field.detach().to("cpu", storage).contiguous().numpy()
                     for field in (means_m, log_radii_m, opacity_logits, rgb)]


def composite_cpu(screen: ScreenGaussians, width: int, height: int, background_rgb: torch.Tensor) -> RenderOutput:
    """Composite screen-space Gaussians with the numba kernels; outputs on the inputs' device and dtype."""
    # cpu_kernel's column order; autograd splits the packed rows' gradients back into the fields
    packed = torch.cat([screen.means_px, screen.conics_px, screen.bounds_px.detach()[:, None], screen.depths_m[:, None],
                        screen.opacity[:, None], screen.rgb], dim=1)
    return composite_packed(packed, width, height, background_rgb)


def composite_packed(packed: torch.Tensor, width: int, height: int, background_rgb: torch.Tensor) -> RenderOutput:
    """Composite packed screen-space rows (N, cpu_kernel.PACKED_COLUMNS) with the numba kernels; outputs on the rows'
    device and dtype, differentiable w.r.t. every column but the bound."""
    rgb, depth, silhouette = _CpuComposite.apply(packed, width, height, background_rgb)
    return RenderOutput(rgb=rgb, depth_m=depth, silhouette=silhouette)


class _CpuProject(torch.autograd.Function):
    """Autograd wrapper of :func:`cpu_kernel.project` and :func:`cpu_kernel.project_backward`: Gaussians and a fixed
    ``camera_from_world`` (4, 4) float64 in, packed screen-space rows out (the Gaussians' dtype and device). The
    fast twin of ``camera_frame_means`` and ``project_to_screen`` under autograd, for renders whose pose is not
    optimised."""

    @staticmethod
    def forward(ctx, means_m, log_radii_m, opacity_logits, rgb, camera_from_world, camera):
        storage, arrays = _projection_arrays(means_m, log_radii_m, opacity_logits, rgb)
        matrix = camera_from_world.detach().to("cpu", torch.float64).numpy()
        packed = cpu_kernel.project(*arrays, matrix, camera)
        ctx.kernel_inputs = (arrays[:3], matrix, camera)
        ctx.storage, ctx.dtype, ctx.device = storage, means_m.dtype, means_m.device
        return torch.from_numpy(packed).to(device=means_m.device, dtype=means_m.dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_packed):
        (means_m, log_radii_m, opacity_logits), matrix, camera = ctx.kernel_inputs
        # As it comes (column-major from composite_backward): a contiguous copy would cost more than the strided reads.
        grads = cpu_kernel.project_backward(means_m, log_radii_m, opacity_logits, matrix, camera,
                                            grad_packed.detach().to("cpu", ctx.storage).numpy())
        grad_means, grad_log_radii, grad_opacity_logits = (
            torch.from_numpy(grad).to(device=ctx.device, dtype=ctx.dtype) for grad in grads)
        grad_rgb = grad_packed[:, cpu_kernel.RED : cpu_kernel.RED + 3]
        return grad_means, grad_log_radii, grad_opacity_logits, grad_rgb, None, None


def _kernel_array(tensor: torch.Tensor) -> np.ndarray:
    """A C-contiguous CPU float32 or float64 array of ``tensor`` (the kernels read either as float64), copied only when needed."""
    dtype = tensor.dtype if tensor.dtype in (torch.float32, torch.float64) else torch.float64
    return np.ascontiguousarray(tensor.detach().to("cpu", dtype).numpy())


class _CpuComposite(torch.autograd.Function):
    """Autograd wrapper of :mod:`cpu_kernel`'s compositing: packed rows in, the three maps out."""

    @staticmethod
    def forward(ctx, packed, width, height, background_rgb):
        # Stored in float32 unless the rows are float64: exact either way (the kernels compute in float64), and
        # float32 rows halve the memory traffic of binning and compositing.
        storage = torch.float64 if packed.dtype == torch.float64 else torch.float32
        rows = packed.detach().to("cpu", storage).contiguous().numpy()
        background = background_rgb.detach().to("cpu", torch.float64).numpy()
        # Maps and gradients come out in the Gaussians' dtype straight from the kernels (float64 inside).
        numpy_dtype = np.float64 if packed.dtype == torch.float64 else np.float32
        bins = cpu_kernel.bin_tiles(rows, width, height)
        colour, depth, silhouette, state = cpu_kernel.composite_forward(bins, width, height, background, numpy_dtype)
        ctx.kernel_inputs = (bins, state, background, numpy_dtype)
        ctx.dtype, ctx.device = packed.dtype, packed.device
        return tuple(
            torch.from_numpy(image).to(device=packed.device, dtype=packed.dtype) for image in (colour, depth, silhouette)
        )

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_rgb, grad_depth, grad_silhouette):
        bins, state, background, numpy_dtype = ctx.kernel_inputs
        image_grads = [_kernel_array(grad) for grad in (grad_rgb, grad_depth, grad_silhouette)]
        grads = torch.from_numpy(cpu_kernel.composite_backward(bins, state, background, *image_grads, numpy_dtype))
        return grads.to(device=ctx.device, dtype=ctx.dtype), None, None, None
