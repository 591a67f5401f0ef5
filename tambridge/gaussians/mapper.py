"""The online Gaussian map (paper Sec. 3.4): its parameters, their Adam state, and the keyframe anchors.

Every Gaussian is *anchored* to the mapping view that created it: its mean is stored in that view's camera
frame, and the world mean is ``world_from_anchor @ mean_anchor``. When loop closure or bundle adjustment moves
a keyframe, :meth:`GaussianMap.set_anchor_pose` moves all the Gaussians it created with it, rigidly and
exactly, so a corrected trajectory does not tear a map built on the old poses (SplaTAM and MonoGS have no loop
closure and store world means).

Adam runs on the raw parameters (anchor-frame means, colour, log radius, opacity logit) with per-Gaussian step
counts, so Gaussians added late get the same bias-corrected first steps as the first ones did.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import cv2
import numpy as np
import torch

from tambridge.camera import Camera
from tambridge.gaussians.config import MapperConfig
from tambridge.state import attribute_state, restore_attributes
from tambridge.gaussians.adam_kernel import adam_step_numba
from tambridge.gaussians.losses import map_loss
from tambridge.gaussians.model import (
    FIELDS,
    NEAR_PLANE_M,
    GaussianTensors,
    RenderOutput,
    camera_frame_means,
    project_to_screen,
)
from tambridge.gaussians.rasterizer import render

SILHOUETTE_FLOOR = 1e-6
"""Silhouettes below this count as nothing rendered."""
ADAM_BETAS = (0.9, 0.999)
ADAM_EPS = 1e-15  # 3DGS's value: radii and opacities get tiny gradients that a larger eps would swamp
MIN_EXPOSURE_FIT_PIXELS = 64
"""Fewer covered pixels than this fix no exposure (:func:`fit_exposure`)."""


@dataclasses.dataclass
class ViewImages:
    """A view's frame at the mapping resolution: rgb (H, W, 3) float32 in [0, 1], depth_m (H, W) float32 (0 = invalid),
    colour_valid (H, W) bool where the colour has data (None: everywhere; undistortion leaves a border without)."""

    rgb: torch.Tensor
    depth_m: torch.Tensor
    colour_valid: torch.Tensor | None = None

    def to(self, device: torch.device) -> "ViewImages":
        """The same images on ``device``."""
        valid = None if self.colour_valid is None else self.colour_valid.to(device)
        return ViewImages(self.rgb.to(device), self.depth_m.to(device), valid)


def backproject(depth_m: torch.Tensor, camera: Camera, mask: torch.Tensor) -> torch.Tensor:
    """(M, 3) camera-frame points of the pixels where ``mask`` (H, W) holds, from ``depth_m`` (H, W), in mask's row-major order."""
    rows, columns = torch.nonzero(mask, as_tuple=True)
    z = depth_m[rows, columns]
    return camera.backproject_torch(torch.stack([columns, rows], dim=1).to(z.dtype), z)


def nearest_measured_depth_m(depth_m: torch.Tensor) -> torch.Tensor:
    """(H, W) ``depth_m`` with every pixel without depth (0) given the depth of the nearest pixel with one (Euclidean
    distance in pixels), all 0 where none has depth: a guess for surfaces the sensor did not measure (too close,
    dark, shiny) that a view still shows."""
    depth = depth_m.cpu().numpy()
    measured = depth > 0
    if measured.all() or not measured.any():
        return depth_m.clone()
    # Each measured pixel is a zero of the input and gets its own label; every other pixel takes its nearest one's.
    _, labels = cv2.distanceTransformWithLabels((~measured).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE,
                                                labelType=cv2.DIST_LABEL_PIXEL)
    depth_of_label = np.zeros(int(labels.max()) + 1, depth.dtype)
    depth_of_label[labels[measured]] = depth[measured]
    return torch.from_numpy(depth_of_label[labels]).to(depth_m.device)


def surface_depth_m(depth_m: torch.Tensor, silhouette: torch.Tensor) -> torch.Tensor:
    """(H, W) rendered depth normalised by the silhouette (the depth of the surface the Gaussians form), 0 where
    nothing is rendered. ``depth_m`` is the unnormalised alpha-blended depth the rasteriser returns."""
    covered = silhouette > SILHOUETTE_FLOOR
    return torch.where(covered, depth_m / silhouette.clamp(min=SILHOUETTE_FLOOR), torch.zeros_like(depth_m))


def render_exposure(gaussians: GaussianTensors, camera: Camera, world_from_camera: np.ndarray,
                    backend: str = "auto") -> RenderOutput:
    """A view rendered as its camera recorded it. ``world_from_camera`` (4, 4): one render. (K, 4, 4), K odd: the
    poses over the view's exposure (:mod:`tambridge.bridge.blur`); colour is the mean of the K renders (motion
    blur: a sensor integrates the light over the exposure), depth and silhouette are the middle pose's, the
    frame's own (a depth camera's exposure is short: its depth is sharp at the frame's time)."""
    poses = np.asarray(world_from_camera, np.float64)
    if poses.ndim == 2:
        return render(gaussians, camera, poses, backend=backend)
    middle = len(poses) // 2
    renders = [render(gaussians, camera, pose, backend=backend) for pose in poses]
    rgb = torch.stack([output.rgb for output in renders]).mean(dim=0)
    return RenderOutput(rgb, renders[middle].depth_m, renders[middle].silhouette)


def densify_mask(observed_depth_m: torch.Tensor, rendered: RenderOutput, silhouette_threshold: float, depth_factor: float) -> torch.Tensor:
    """(H, W) bool: pixels with valid depth that the map does not explain yet.

    Either the border mask is below ``silhouette_threshold`` (uncovered or half-covered) or the rendered surface is
    far behind the observed one (something new in front of the map: more than ``depth_factor`` times the median
    depth residual over the covered pixels).
    """
    with torch.no_grad():
        valid = observed_depth_m > 0
        uncovered = rendered.silhouette < silhouette_threshold
        surface = surface_depth_m(rendered.depth_m, rendered.silhouette)
        covered = valid & ~uncovered
        behind = torch.zeros_like(valid)
        if bool(covered.any()):
            residual = surface - observed_depth_m
            median = residual[covered].abs().median()
            behind = covered & (residual > depth_factor * median)
        return valid & (uncovered | behind)


class ViewExposure:
    """A mapping view's exposure: the per-channel affine map ``exp(log_gain) * C + bias`` from the map's colours
    to what this view's camera recorded (auto exposure and white balance change along a real sequence).

    Without it the map's colours follow whichever views were optimised last, and earlier parts of the sequence
    are rendered too bright or too dark.
    Gain and colours are ambiguous: scaling every exposure of a window and dividing the colours its views see
    leaves the loss unchanged, so without a pull the exposures of the views optimised together random-walk away
    from the identity, and the map's colours with them (the first view, ``frozen`` at the identity, holds only
    the colours it sees and only while it is in the window). ``prior`` pulls the log gains and biases to 0 (an L2
    prior of weight ``prior / 2``, as Adam's weight decay), so that the map keeps the colours of a typical view and
    the exposures take only what real changes of the camera's exposure need; :meth:`rebase` (with
    :meth:`GaussianMap.recolour`) moves the colour scale itself exactly.
    ``parameters`` (2, 3): log gains, biases; optimised with Adam at ``learning_rate``.
    A new exposure lives on ``device``, or on the device of the ``parameters`` it starts from.
    """

    def __init__(self, parameters: torch.Tensor | None = None, learning_rate: float = 0.0, frozen: bool = False,
                 device: str | torch.device = "cpu", prior: float = 0.0) -> None:
        initial = torch.zeros((2, 3), device=device) if parameters is None else parameters.detach().clone()
        assert initial.shape == (2, 3), initial.shape
        self.parameters = initial.requires_grad_(not frozen)
        self.frozen = frozen
        self._optimiser = None if frozen else torch.optim.Adam([self.parameters], lr=learning_rate, eps=ADAM_EPS,
                                                                weight_decay=prior)

    def to(self, device: str | torch.device) -> ViewExposure:
        """This exposure on ``device``, Adam state included: itself when it is there already, else a copy."""
        if self.parameters.device == torch.device(device):
            return self
        moved = ViewExposure(self.parameters.to(device), frozen=self.frozen)
        if self._optimiser is not None:
            # Restores the learning rate and prior too; Adam casts its moments to the device of their parameter.
            moved._optimiser.load_state_dict(self._optimiser.state_dict())
        return moved

    def apply(self, rgb: torch.Tensor) -> torch.Tensor:
        """(H, W, 3) map colours -> this view's colours (differentiable in both)."""
        return rgb * torch.exp(self.parameters[0]) + self.parameters[1]

    def invert(self, rgb: torch.Tensor) -> torch.Tensor:
        """(M, 3) colours seen by this view -> map colours (no gradient)."""
        with torch.no_grad():
            return (rgb - self.parameters[1]) * torch.exp(-self.parameters[0])

    def rebase(self, reference: torch.Tensor) -> None:
        """Re-express this exposure for map colours recoloured by the exposure ``reference`` (2, 3) (colours
        ``C' = exp(log_gain_ref) C + bias_ref``): afterwards :meth:`apply` gives of ``C'`` what it gave of ``C``."""
        with torch.no_grad():
            log_gain = self.parameters[0] - reference[0]
            self.parameters[1] -= torch.exp(log_gain) * reference[1]
            self.parameters[0] = log_gain

    def reset(self, parameters: torch.Tensor) -> None:
        """Set the log gains and biases to ``parameters`` (2, 3) and drop Adam's moments, which belong to the old
        ones."""
        with torch.no_grad():
            self.parameters.copy_(parameters)
        if self._optimiser is not None:
            self._optimiser.state.clear()

    def step(self) -> None:
        """One Adam step on the gradient the last backward pass left (none when frozen), then clear it."""
        if self._optimiser is not None and self.parameters.grad is not None:
            self._optimiser.step()
            self._optimiser.zero_grad(set_to_none=True)

    def state_dict(self) -> dict:
        """Parameters (on the CPU), whether frozen, and the Adam state (None when frozen), for checkpoints."""
        return {"parameters": self.parameters.detach().cpu(), "frozen": self.frozen,
                "adam": None if self._optimiser is None else self._optimiser.state_dict()}

    @classmethod
    def from_state_dict(cls, state: dict) -> ViewExposure:
        """The exposure :meth:`state_dict` describes, on the device of its parameters."""
        exposure = cls(state["parameters"], frozen=state["frozen"])
        if exposure._optimiser is not None:
            exposure._optimiser.load_state_dict(state["adam"])  # the learning rate and prior too
        return exposure


def affine_colour_fit(rendered_rgb: torch.Tensor, observed_rgb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per channel, the gain and bias (3,) each, float64, of the affine map that takes the ``rendered_rgb`` (M, 3)
    colours closest to the ``observed_rgb`` (M, 3) ones in least squares (closed form; a channel without spread in
    ``rendered_rgb`` gets a gain of NaN)."""
    rendered, observed = rendered_rgb.double(), observed_rgb.double()
    rendered_mean, observed_mean = rendered.mean(0), observed.mean(0)
    variance = ((rendered - rendered_mean) ** 2).mean(0)
    covariance = ((rendered - rendered_mean) * (observed - observed_mean)).mean(0)
    gain = covariance / variance
    return gain, observed_mean - gain * rendered_mean


def fit_exposure(rendered_rgb: torch.Tensor, observed_rgb: torch.Tensor, mask: torch.Tensor) -> torch.Tensor | None:
    """The :class:`ViewExposure` parameters (2, 3), log gains and biases, whose per-channel affine map takes the
    ``rendered_rgb`` (H, W, 3) map colours closest to the ``observed_rgb`` (H, W, 3) ones over the ``mask`` (H, W)
    pixels (:func:`affine_colour_fit`); None where fewer than :data:`MIN_EXPOSURE_FIT_PIXELS` are masked or a
    channel's best gain is not a positive number (no exposure explains it)."""
    if int(mask.sum()) < MIN_EXPOSURE_FIT_PIXELS:
        return None
    gain, bias = affine_colour_fit(rendered_rgb[mask], observed_rgb[mask])
    if not bool((torch.isfinite(gain) & (gain > 0)).all()):
        return None
    return torch.stack([gain.log(), bias]).to(rendered_rgb.dtype)


def adam_step_torch(params: dict, grads: dict, exp_avg: dict, exp_avg_sq: dict, steps: torch.Tensor,
                    learning_rates: dict[str, float], betas: tuple[float, float], eps: float) -> torch.Tensor:
    """One Adam step (Kingma & Ba 2015), in place on ``params``, ``exp_avg`` and ``exp_avg_sq`` (dicts of tensors
    (M, ...) by field), on the Gaussians with a nonzero gradient in some field of ``grads``, at ``learning_rates`` by
    field; colours clamped to [0, 1]. Returns the new step counts (M,). The twin of the CPU kernel, and the step on a
    GPU (torch.optim.Adam is the twin the tests compare it with).

    A Gaussian without a gradient has a zero gradient in every field: with its decay factors and step size set to 1, 1
    and 0 the same in-place expressions leave its moments and parameters as they were, so no masked copies are
    made."""
    beta1, beta2 = betas
    touched = torch.zeros(len(steps), dtype=torch.bool, device=steps.device)
    for grad in grads.values():
        touched |= (grad.reshape(len(steps), -1) != 0).any(dim=1)
    mask = touched.to(steps.dtype)
    steps = steps + mask
    decay1 = 1.0 - (1.0 - beta1) * mask
    decay2 = 1.0 - (1.0 - beta2) * mask
    step_size = mask / (1.0 - beta1 ** steps.clamp(min=1))
    root_correction = torch.rsqrt(1.0 - beta2 ** steps.clamp(min=1))
    with torch.no_grad():
        for name, grad in grads.items():
            shape = (-1,) + (1,) * (grad.dim() - 1)
            exp_avg[name].mul_(decay1.view(shape)).add_(grad, alpha=1.0 - beta1)
            exp_avg_sq[name].mul_(decay2.view(shape)).addcmul_(grad, grad, value=1.0 - beta2)
            denominator = exp_avg_sq[name].sqrt().mul_(root_correction.view(shape)).add_(eps)
            scaled = exp_avg[name] * (learning_rates[name] * step_size).view(shape)
            params[name].addcdiv_(scaled, denominator, value=-1.0)
        # Colours are optimised directly (as SplaTAM does) and kept in the displayable range.
        params["rgb"].clamp_(0.0, 1.0)
    return steps


class GaussianMap:
    """Isotropic Gaussians anchored to mapping views, with their Adam state.

    ``anchor ids`` are the mapper's names for mapping views (the pipeline uses keyframe ids). Tensors live on
    ``device`` in float32; anchor poses in float64.
    """

    def __init__(self, config: MapperConfig, device: str | torch.device = "cpu") -> None:
        self.config = config
        self.device = torch.device(device)
        self._params = {
            "means_anchor_m": torch.zeros((0, 3), device=self.device),
            "rgb": torch.zeros((0, 3), device=self.device),
            "log_radii_m": torch.zeros(0, device=self.device),
            "opacity_logits": torch.zeros(0, device=self.device),
        }
        self._exp_avg = {name: torch.zeros_like(value) for name, value in self._params.items()}
        self._exp_avg_sq = {name: torch.zeros_like(value) for name, value in self._params.items()}
        self._steps = torch.zeros(0, device=self.device)
        self._anchor_rows = torch.zeros(0, dtype=torch.long, device=self.device)
        self._anchor_ids: list[int] = []
        self._world_from_anchor = torch.zeros((0, 4, 4), dtype=torch.float64, device=self.device)

    @property
    def learning_rates(self) -> dict[str, float]:
        """Adam's learning rate of each field, from ``config`` (a config replaced later takes effect)."""
        return {"means_anchor_m": self.config.lr_means_m, "rgb": self.config.lr_rgb,
                "log_radii_m": self.config.lr_log_radii, "opacity_logits": self.config.lr_opacity_logits}

    def __len__(self) -> int:
        return int(self._params["rgb"].shape[0])

    # ---- anchors -------------------------------------------------------------------------------------------

    def set_anchor_pose(self, anchor_id: int, world_from_anchor: np.ndarray) -> None:
        """Register an anchor or move it (4x4 ``world_from_anchor``); its Gaussians move with it rigidly."""
        pose = torch.as_tensor(np.asarray(world_from_anchor, np.float64), device=self.device)
        assert pose.shape == (4, 4), pose.shape
        if anchor_id in self._anchor_ids:
            self._world_from_anchor[self._anchor_ids.index(anchor_id)] = pose
        else:
            self._anchor_ids.append(anchor_id)
            self._world_from_anchor = torch.cat([self._world_from_anchor, pose[None]], dim=0)

    # ---- the Gaussians --------------------------------------------------------------------------------------

    def gaussians(self, params: dict[str, torch.Tensor] | None = None, rows: torch.Tensor | None = None) -> GaussianTensors:
        """World-frame :class:`GaussianTensors` of the map.

        ``rows`` (M,) long picks a subset; ``params`` then holds that subset's raw parameters (the leaves being
        optimised), else the map's own are used.
        """
        if params is None:
            params = self._params if rows is None else {name: value[rows] for name, value in self._params.items()}
        anchor_rows = self._anchor_rows if rows is None else self._anchor_rows[rows]
        world_from_anchor = self._world_from_anchor.to(params["means_anchor_m"].dtype)[anchor_rows]  # (M, 4, 4)
        means_world = torch.einsum("nij,nj->ni", world_from_anchor[:, :3, :3], params["means_anchor_m"]) + world_from_anchor[:, :3, 3]
        return GaussianTensors(means_world, params["rgb"], params["log_radii_m"], params["opacity_logits"])

    def visible_rows(self, camera: Camera, world_from_camera: np.ndarray) -> torch.Tensor:
        """(M,) long indices, ascending, of the Gaussians whose bounding disc (of the 3-sigma ellipse) can touch the
        image of ``camera`` at this pose (4, 4), or at any of these poses (K, 4, 4): exactly those the CPU kernel
        bins."""
        with torch.no_grad():
            gaussians = self.gaussians()
            inside = torch.zeros(len(gaussians.means_m), dtype=torch.bool, device=gaussians.means_m.device)
            for pose in np.asarray(world_from_camera, np.float64).reshape(-1, 4, 4):
                screen = project_to_screen(gaussians, camera_frame_means(gaussians, torch.as_tensor(pose)), camera)
                reach = screen.bounds_px
                u, v = screen.means_px[:, 0], screen.means_px[:, 1]
                inside |= (
                    (screen.depths_m > NEAR_PLANE_M)
                    & (u + reach >= 0) & (u - reach <= camera.width - 1)
                    & (v + reach >= 0) & (v - reach <= camera.height - 1)
                )
            return torch.nonzero(inside).squeeze(1)

    def render(self, camera: Camera, world_from_camera: np.ndarray) -> RenderOutput:
        """Render the map without gradients (evaluation, densification)."""
        with torch.no_grad():
            return render(self.gaussians(), camera, world_from_camera, backend=self.config.backend)

    def add(self, anchor_id: int, means_anchor_m: torch.Tensor, rgb: torch.Tensor, radii_m: torch.Tensor) -> None:
        """Append M Gaussians created by ``anchor_id``: means (M, 3) in its camera frame, rgb (M, 3), radii (M,) metres.

        They start at opacity ``config.initial_opacity`` with fresh Adam state.
        """
        count = means_anchor_m.shape[0]
        assert means_anchor_m.shape == (count, 3) and rgb.shape == (count, 3) and radii_m.shape == (count,)
        if anchor_id not in self._anchor_ids:
            raise KeyError(f"anchor {anchor_id} has no pose; call set_anchor_pose first")
        initial_logit = float(np.log(self.config.initial_opacity / (1.0 - self.config.initial_opacity)))
        new = {
            "means_anchor_m": means_anchor_m.to(self.device, torch.float32),
            "rgb": rgb.to(self.device, torch.float32),
            "log_radii_m": torch.log(radii_m).to(self.device, torch.float32),
            "opacity_logits": torch.full((count,), initial_logit, device=self.device),
        }
        for name in FIELDS:
            self._params[name] = torch.cat([self._params[name], new[name]])
            self._exp_avg[name] = torch.cat([self._exp_avg[name], torch.zeros_like(new[name])])
            self._exp_avg_sq[name] = torch.cat([self._exp_avg_sq[name], torch.zeros_like(new[name])])
        self._steps = torch.cat([self._steps, torch.zeros(count, device=self.device)])
        row = self._anchor_ids.index(anchor_id)
        self._anchor_rows = torch.cat([self._anchor_rows, torch.full((count,), row, dtype=torch.long, device=self.device)])

    def keep(self, kept: torch.Tensor) -> None:
        """Keep only the Gaussians where ``kept`` (N,) bool holds, with their Adam state."""
        for state in (self._params, self._exp_avg, self._exp_avg_sq):
            for name in FIELDS:
                state[name] = state[name][kept]
        self._steps = self._steps[kept]
        self._anchor_rows = self._anchor_rows[kept]

    def densify(self, anchor_id: int, camera: Camera, images: ViewImages, rendered: RenderOutput | None,
                exposure: ViewExposure | None = None) -> int:
        """Add a Gaussian at every pixel of the view that the map does not explain (all valid pixels when empty).

        ``anchor_id`` is the view (its pose set already); ``rendered`` the map rendered at that pose (None: empty map).
        A new Gaussian sits on the back-projected pixel with a radius of one pixel, ``r = d / f`` (eq. 8), and the
        pixel's colour (in map colours through ``exposure`` when given). Returns how many were added.
        """
        if rendered is None:
            mask = images.depth_m > 0
        else:
            mask = densify_mask(images.depth_m, rendered, self.config.densify_silhouette, self.config.densify_depth_factor)
        return self._add_pixels(anchor_id, camera, images, mask, exposure)

    def densify_unmeasured(self, anchor_id: int, camera: Camera, images: ViewImages, rendered: RenderOutput | None,
                           exposure: ViewExposure | None, silhouette_threshold: float) -> int:
        """Add a one-pixel Gaussian (as :meth:`densify`) at each pixel of the view without measured depth where the
        map leaves a hole (its silhouette in ``rendered``, the map at the view's pose, below
        ``silhouette_threshold``; None: an empty map) and the colour has data, at :func:`nearest_measured_depth_m`:
        surfaces the depth camera missed (too close, dark, shiny) that the colour still shows. Returns how many
        were added (none at a threshold of 0)."""
        if silhouette_threshold <= 0:
            return 0
        with torch.no_grad():
            mask = images.depth_m <= 0
            if rendered is not None:
                mask &= rendered.silhouette < silhouette_threshold
            if images.colour_valid is not None:
                mask &= images.colour_valid
            depth_m = nearest_measured_depth_m(images.depth_m)
            mask &= depth_m > 0
        return self._add_pixels(anchor_id, camera, dataclasses.replace(images, depth_m=depth_m), mask, exposure)

    def densify_colour_error(self, anchor_id: int, camera: Camera, images: ViewImages, exposure: ViewExposure | None,
                             threshold: float, fraction: float, world_from_subposes: np.ndarray | None = None) -> int:
        """Add a one-pixel Gaussian (as :meth:`densify`) at the pixels whose colour error is worst: the map rendered
        at the view's pose (through ``exposure``) against ``images``, mean absolute error over the channels above
        ``threshold``, at most ``fraction`` of the view's pixels, only where depth is valid and the colour has data.
        At a finer ``camera`` than the mapping one, this adds detail that the map's coarser Gaussians blur.
        ``world_from_subposes`` (K, 4, 4): a blurred view's poses over its exposure, the map rendered blurred as
        the frame is (:func:`render_exposure`). Returns how many were added."""
        if not len(self) or threshold <= 0 or fraction <= 0:
            return 0
        with torch.no_grad():
            world_from_camera = self._world_from_anchor[self._anchor_ids.index(anchor_id)].cpu().numpy()
            rendered = render_exposure(self.gaussians(), camera, world_from_camera if world_from_subposes is None
                                       else world_from_subposes, backend=self.config.backend).rgb
            if exposure is not None:
                rendered = exposure.apply(rendered)
            error = (rendered.clamp(0.0, 1.0) - images.rgb).abs().mean(dim=2)
            valid = images.depth_m > 0
            if images.colour_valid is not None:
                valid &= images.colour_valid
            error = torch.where(valid, error, torch.zeros_like(error))
            budget = int(fraction * error.numel())
            mask = error > threshold
            if int(mask.sum()) > budget:
                cutoff = torch.topk(error.flatten(), budget + 1).values[-1] if budget else error.max()
                mask &= error > cutoff
        return self._add_pixels(anchor_id, camera, images, mask, exposure)

    def _add_pixels(self, anchor_id: int, camera: Camera, images: ViewImages, mask: torch.Tensor,
                    exposure: ViewExposure | None) -> int:
        """Add a Gaussian at each pixel where ``mask`` (H, W) holds: back-projected into the view's (the anchor's)
        camera frame, radius one pixel ``r = d / f`` (eq. 8), the pixel's colour in map colours through ``exposure``."""
        points = backproject(images.depth_m, camera, mask)
        colours = images.rgb[mask] if exposure is None else exposure.invert(images.rgb[mask]).clamp(0.0, 1.0)
        self.add(anchor_id, points, colours, points[:, 2] / camera.mean_focal_px)
        return int(points.shape[0])

    def unexplained_fraction(self, camera: Camera, world_from_camera: np.ndarray, depth_m: torch.Tensor) -> float:
        """Share of the valid pixels of ``depth_m`` (H, W, at ``camera``'s size) that :meth:`densify` would fill
        at this pose (1 with an empty map, 0 without valid depth): how much of the view the map lacks."""
        valid = int((depth_m > 0).sum())
        if valid == 0:
            return 0.0
        if not len(self):
            return 1.0
        mask = densify_mask(depth_m, self.render(camera, world_from_camera), self.config.densify_silhouette,
                            self.config.densify_depth_factor)
        return int(mask.sum()) / valid

    def prune(self, camera: Camera, world_from_camera: np.ndarray) -> int:
        """Remove Gaussians of opacity below ``tau`` and those bigger than ``prune_radius_px`` pixels in this view
        (radius ``f r / z``).

        Returns how many were removed.
        """
        with torch.no_grad():
            opacity = torch.sigmoid(self._params["opacity_logits"])
            means_camera = camera_frame_means(self.gaussians(), torch.as_tensor(np.asarray(world_from_camera, np.float64)))
            depth = means_camera[:, 2].clamp(min=1e-3)
            # The Gaussian's own size in pixels, f r / z, not its footprint's long axis (up to ~1.25x larger off
            # axis): on 7-Scenes 0-699 the long axis pruned splats the map needed (docs/benchmarks.md).
            radius_px = camera.mean_focal_px * torch.exp(self._params["log_radii_m"]) / depth
            oversized = (means_camera[:, 2] > 0) & (radius_px > self.config.prune_radius_px)
            kept = (opacity >= self.config.tau) & ~oversized
        removed = len(self) - int(kept.sum())
        if removed:
            self.keep(kept)
        return removed

    # ---- optimisation ---------------------------------------------------------------------------------------

    def optimise(self, camera: Camera, views: Sequence[tuple[np.ndarray, ViewImages]], schedule: Sequence[int],
                 exposures: Sequence[ViewExposure | None] | None = None, learning_rate_scale: float = 1.0,
                 w_colour_squared: float = 0.0) -> list[float]:
        """Adam steps of the map loss with the poses fixed: step k renders ``views[schedule[k]]``; returns the losses.

        ``views`` are ``(world_from_camera, images)`` pairs at ``camera``'s resolution, the pose (4, 4) or a
        blurred view's poses over its exposure (K, 4, 4), rendered by :func:`render_exposure`. Only the Gaussians
        that can touch one of the views take part: they are gathered once into contiguous tensors with their Adam
        state, stepped, and scattered back, so the cost follows the views, not the size of the map. A Gaussian
        that gets no gradient in a step (outside that step's view) does not move and its Adam state is unchanged.
        ``exposures`` (one per view, or None) maps the render to the view's exposure before the loss; those not
        frozen are optimised along with the Gaussians. The Gaussians' learning rates are ``learning_rate_scale``
        times ``config.lr_*``; ``w_colour_squared`` weighs the squared colour error in :func:`map_loss`.
        """
        if not schedule or len(self) == 0:
            return []
        rows = self.visible_rows(camera, np.concatenate([np.asarray(poses).reshape(-1, 4, 4) for poses, _ in views]))
        params = {name: value[rows].clone() for name, value in self._params.items()}
        exp_avg = {name: value[rows].clone() for name, value in self._exp_avg.items()}
        exp_avg_sq = {name: value[rows].clone() for name, value in self._exp_avg_sq.items()}
        steps = self._steps[rows].clone()
        world_from_anchor = self._world_from_anchor.to(torch.float32)[self._anchor_rows[rows]]
        rotations, translations = world_from_anchor[:, :3, :3], world_from_anchor[:, :3, 3]
        losses = []
        for view_index in schedule:
            world_from_camera, images = views[view_index]
            leaves = {name: value.requires_grad_(True) for name, value in params.items()}
            means_world = torch.einsum("nij,nj->ni", rotations, leaves["means_anchor_m"]) + translations
            gaussians = GaussianTensors(means_world, leaves["rgb"], leaves["log_radii_m"], leaves["opacity_logits"])
            rendered = render_exposure(gaussians, camera, world_from_camera, backend=self.config.backend)
            exposure = exposures[view_index] if exposures is not None else None
            rendered_rgb = rendered.rgb if exposure is None else exposure.apply(rendered.rgb)
            observed_rgb = images.rgb
            if images.colour_valid is not None:
                # Where the frame has no colour the target is the render itself: those pixels pull on nothing.
                observed_rgb = torch.where(images.colour_valid[..., None], observed_rgb, rendered_rgb.detach())
            loss = map_loss(rendered_rgb, rendered.depth_m, observed_rgb, images.depth_m,
                            self.config.zeta, self.config.w_depth, self.config.w_colour, w_colour_squared)
            loss.backward()
            params = {name: leaf.detach() for name, leaf in leaves.items()}
            steps = self._adam_step(params, {name: leaf.grad for name, leaf in leaves.items()}, exp_avg, exp_avg_sq, steps,
                                    learning_rate_scale)
            if exposure is not None:
                exposure.step()
            losses.append(float(loss.detach()))
        for name in FIELDS:
            self._params[name][rows] = params[name]
            self._exp_avg[name][rows] = exp_avg[name]
            self._exp_avg_sq[name][rows] = exp_avg_sq[name]
        self._steps[rows] = steps
        return losses

    def _adam_step(self, params: dict, grads: dict, exp_avg: dict, exp_avg_sq: dict, steps: torch.Tensor,
                   learning_rate_scale: float = 1.0) -> torch.Tensor:
        """One Adam step (Kingma & Ba 2015), in place, on the Gaussians with a gradient, at ``learning_rate_scale``
        times the configured learning rates; returns their step counts (M,). On the CPU in one numba pass
        (:func:`tambridge.gaussians.adam_kernel.adam_step_numba`), elsewhere :func:`adam_step_torch`."""
        learning_rates = {name: rate * learning_rate_scale for name, rate in self.learning_rates.items()}
        step = adam_step_numba if steps.device.type == "cpu" else adam_step_torch
        return step(params, grads, exp_avg, exp_avg_sq, steps, learning_rates, ADAM_BETAS, ADAM_EPS)

    def recolour(self, exposure: ViewExposure) -> None:
        """Replace every Gaussian's colour by ``exposure.apply`` of it (kept in [0, 1]): the map in another view's
        colours (see :meth:`ViewExposure.rebase`)."""
        with torch.no_grad():
            self._params["rgb"] = exposure.apply(self._params["rgb"]).clamp(0.0, 1.0)

    def world_gaussians(self) -> GaussianTensors:
        """Detached world-frame Gaussians (for export)."""
        with torch.no_grad():
            return self.gaussians()

    def state_dict(self) -> dict:
        """Parameters, Adam state, anchors and anchor poses (tensors on the CPU), for checkpoints."""
        return _tensors_to(attribute_state(self, ("config", "device")), torch.device("cpu"))

    def load_state_dict(self, state: dict) -> None:
        """Continue from :meth:`state_dict` (on a map built with the same config); tensors go to this map's device."""
        restore_attributes(self, _tensors_to(state, self.device))


def _tensors_to(value, device: torch.device):
    """``value`` with every tensor in it (through dicts and lists) on ``device``."""
    if isinstance(value, torch.Tensor):
        return value.to(device)
    if isinstance(value, dict):
        return {key: _tensors_to(item, device) for key, item in value.items()}
    if isinstance(value, list):
        return [_tensors_to(item, device) for item in value]
    return value
