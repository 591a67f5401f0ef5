"""Border-mask gates and the joint pose refinement of the Fusion Bridge (paper Sec. 3.3).

With the Gaussians fixed, the pose of a mapping view is refined from the frontend's estimate by minimising
``w1 L_rpj + w2 L_colour + w3 L_depth`` over a right perturbation ``xi = (rho, phi)`` of ``world_from_camera``:

- ``L_rpj``: mean pixel distance between the keyframe's matched keypoints and the projections of their map points
  (eq. 1; pixels of the refinement image), the anchor to the feature-based tracking;
- ``L_colour``, ``L_depth``: L1 between the rendered and the observed colour / depth over the gated pixels. The
  rendered depth is normalised by the silhouette (the depth of the surface the Gaussians form): at ``M_b = 0.99``
  the raw alpha-blended depth is 1 % short, 2 cm at 2 m, which would pull the pose towards the scene.

A pixel takes part only where the gates pass (eq. 5): observed depth > 0, rendered depth > 0, border mask
(rendered silhouette) ``M_b > gamma``, and its depth residual is not an outlier (below ``depth_outlier_factor``
times the median residual of the other gates' pixels), so that the unfinished borders of the map, holes in the
sensor depth and disocclusions do not pull the pose.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from tambridge.camera import Camera
from tambridge.bridge.config import BridgeConfig
from tambridge.gaussians.losses import masked_l1
from tambridge.gaussians.mapper import surface_depth_m
from tambridge.gaussians.model import GaussianTensors, camera_from_world_tensor
from tambridge.gaussians.rasterizer import render
from tambridge.geometry import exp_se3

# Length of a unit step of the refined twist's translation (L-BFGS's first step is at most one unit long): long
# units overshoot a centimetre-scale error and short ones do not reach it within the evaluation budget.
TWIST_UNIT_M = 0.1


def pixel_gates(
    observed_depth_m: torch.Tensor,
    rendered_depth_m: torch.Tensor,
    silhouette: torch.Tensor,
    gamma: float,
    depth_outlier_factor: float,
) -> torch.Tensor:
    """(H, W) bool: ``D_c > 0 & D_g > 0 & M_b > gamma`` and a depth residual within ``factor * median``.

    observed_depth_m, rendered_depth_m (unnormalised, as rendered), silhouette: (H, W). The residual compares the
    observed depth with the silhouette-normalised rendered depth. Computed without gradients: gates select pixels.
    """
    assert observed_depth_m.shape == rendered_depth_m.shape == silhouette.shape, (observed_depth_m.shape, silhouette.shape)
    with torch.no_grad():
        gates = (observed_depth_m > 0) & (rendered_depth_m > 0) & (silhouette > gamma)
        if not bool(gates.any()):
            return gates
        residual_m = (surface_depth_m(rendered_depth_m, silhouette) - observed_depth_m).abs()
        threshold_m = depth_outlier_factor * residual_m[gates].median()
        return gates & (residual_m <= threshold_m)


def reprojection_error_px(
    camera: Camera,
    world_from_camera: torch.Tensor,
    pose_delta: torch.Tensor | None,
    points_world_m: torch.Tensor,
    keypoints_px: torch.Tensor,
) -> torch.Tensor:
    """Mean over points of ``|u - pi(camera_from_world P)|_2`` in pixels (eq. 1); 0 when no point is in front.

    world_from_camera: (4, 4) float64; pose_delta: (6,) right perturbation or None; points_world_m: (M, 3);
    keypoints_px: (M, 2) in the pixels of ``camera``.
    """
    assert points_world_m.shape[0] == keypoints_px.shape[0], (points_world_m.shape, keypoints_px.shape)
    camera_from_world = camera_from_world_tensor(world_from_camera, pose_delta)
    points_cam = points_world_m.to(torch.float64) @ camera_from_world[:3, :3].T + camera_from_world[:3, 3]
    in_front = points_cam[:, 2] > 1e-3
    if not bool(in_front.any()):
        return torch.zeros((), dtype=torch.float64, device=points_cam.device)
    points_cam, observed = points_cam[in_front], keypoints_px[in_front].to(torch.float64)
    return (camera.project_torch(points_cam) - observed).norm(dim=1).mean()


@dataclasses.dataclass
class RefinementResult:
    """Outcome of :func:`refine_render_pose`: the refined 4x4 ``world_from_camera`` and how the loss went.

    ``loss_initial``/``loss_final``: joint loss at the frontend pose and at the returned pose (the lowest seen);
    ``gated_fraction``: share of the pixels that passed the gates at the frontend pose; ``skipped``: True when the
    frontend pose was kept as it was (too few pixels passed and no point was matched, or the matched points already
    reprojected within the noise floor); ``reprojection_px``: their mean reprojection error at the frontend pose
    (NaN without matched points).
    """

    world_from_camera: np.ndarray
    loss_initial: float
    loss_final: float
    gated_fraction: float
    skipped: bool
    reprojection_px: float = float("nan")


def refine_render_pose(
    gaussians: GaussianTensors,
    camera: Camera,
    world_from_camera: np.ndarray,
    observed_rgb: torch.Tensor,
    observed_depth_m: torch.Tensor,
    points_world_m: np.ndarray,
    keypoints_px: np.ndarray,
    config: BridgeConfig,
    backend: str = "auto",
    colour_weight: float = 1.0,
) -> RefinementResult:
    """Refine ``world_from_camera`` (4, 4) of one view against the fixed ``gaussians`` with L-BFGS on the twist.

    observed_rgb (H, W, 3) in [0, 1] and observed_depth_m (H, W) are the view's frame at ``camera``'s resolution;
    points_world_m (M, 3) / keypoints_px (M, 2) its matched map points and keypoints in ``camera``'s pixels (M may
    be 0). ``config.iterations`` bounds the loss evaluations (one render and its backward pass each). Returns the
    pose of the lowest joint loss seen, so a refinement never makes the loss worse than the frontend's pose.
    ``colour_weight`` (in [0, 1]) scales ``w2``: a blurred view's colours say less about its pose. Where the matched
    points already reproject within ``config.reprojection_floor_px`` at the frontend pose, the frontend pose is kept
    without a render (the tracking is at its noise floor: the map cannot place the view better).

    L-BFGS with a strong-Wolfe line search rather than Adam: Adam's steps stay near its learning rate however small
    the gradient, so in 10 steps it circles the optimum.
    """
    device = gaussians.means_m.device
    start = torch.from_numpy(np.asarray(world_from_camera, dtype=np.float64)).to(device)
    # Translation in units of TWIST_UNIT_M, rotation in units of TWIST_UNIT_M / lever_m radians (a unit step turns
    # points at lever_m as far as a unit translation). In metres the first step overshot, and the line search
    # spent evaluations coming back from it.
    twist_scale = TWIST_UNIT_M * torch.tensor([1.0, 1.0, 1.0] + [1.0 / config.lever_m] * 3, dtype=torch.float64, device=device)
    twist = torch.zeros(6, dtype=torch.float64, device=device, requires_grad=True)
    points = torch.from_numpy(np.asarray(points_world_m, dtype=np.float64).reshape(-1, 3)).to(device)
    keypoints = torch.from_numpy(np.asarray(keypoints_px, dtype=np.float64).reshape(-1, 2)).to(device)
    reprojection_px = float(reprojection_error_px(camera, start, None, points, keypoints)) if len(points) else float("nan")
    if reprojection_px <= config.reprojection_floor_px:
        return RefinementResult(np.asarray(world_from_camera, np.float64).copy(), float("nan"), float("nan"),
                                float("nan"), skipped=True, reprojection_px=reprojection_px)
    with torch.no_grad():
        rendered = render(gaussians, camera, start, torch.zeros(6, dtype=torch.float64, device=device), backend=backend)
        # The gates are drawn once, at the frontend pose: gates redrawn at every step would let the pose lower
        # the loss by moving hard pixels out of the gated set rather than by aligning the view.
        gates = pixel_gates(observed_depth_m, rendered.depth_m, rendered.silhouette, config.gamma, config.depth_outlier_factor)
    gated_fraction = float(gates.sum()) / observed_depth_m.numel()
    if gated_fraction < config.min_gated_fraction and len(points) == 0:
        return RefinementResult(np.asarray(world_from_camera, np.float64).copy(), float("nan"), float("nan"),
                                gated_fraction, skipped=True, reprojection_px=reprojection_px)
    observed_rgb = observed_rgb.to(rendered.rgb.dtype)
    observed_depth_m = observed_depth_m.to(rendered.depth_m.dtype)
    losses: list[tuple[float, np.ndarray]] = []  # (loss, pose delta) of every evaluation

    def joint_loss() -> torch.Tensor:
        optimiser.zero_grad()
        pose_delta = twist * twist_scale
        rendered = render(gaussians, camera, start, pose_delta, backend=backend)
        loss = (
            colour_weight * config.w_colour * masked_l1(rendered.rgb, observed_rgb, gates)
            + config.w_depth * masked_l1(surface_depth_m(rendered.depth_m, rendered.silhouette), observed_depth_m, gates)
        ).to(torch.float64)
        if len(points):
            loss = loss + config.w_reprojection * reprojection_error_px(camera, start, pose_delta, points, keypoints)
        loss.backward()
        losses.append((float(loss.detach()), pose_delta.detach().cpu().numpy().copy()))
        return loss

    optimiser = torch.optim.LBFGS([twist], lr=1.0, max_iter=max(1, config.iterations), max_eval=max(1, config.iterations),
                                  history_size=10, line_search_fn="strong_wolfe", tolerance_grad=1e-12,
                                  tolerance_change=1e-14)
    optimiser.step(joint_loss)
    loss_initial = losses[0][0]
    best_loss, best_delta = min(losses, key=lambda pair: pair[0])
    refined = np.asarray(world_from_camera, np.float64) @ exp_se3(best_delta)
    return RefinementResult(refined, loss_initial, best_loss, gated_fraction, skipped=False, reprojection_px=reprojection_px)
