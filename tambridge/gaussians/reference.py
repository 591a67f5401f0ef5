"""Dense pure-torch compositing: the slow, obviously-correct twin of the CPU kernel (tests and benchmarks only).

Every Gaussian is evaluated at every pixel, sorted by depth, and composited with a cumulative product of
``1 - alpha``; autograd gives the gradients. It applies exactly the cut-offs of :mod:`tambridge.gaussians.model`
(near plane, 3-sigma Mahalanobis cut-off of the EWA footprint, no eps2d dilation, alpha clamp, early stop), so the
fast kernels must agree with it to rounding.
"""

from __future__ import annotations

import torch
import torch.utils.checkpoint

from tambridge.gaussians.model import (
    ALPHA_MAX,
    NEAR_PLANE_M,
    SIGMA_CUTOFF,
    TRANSMITTANCE_MIN,
    RenderOutput,
    ScreenGaussians,
)


def composite_pixels(
    means_px: torch.Tensor,
    conics_px: torch.Tensor,
    depths_m: torch.Tensor,
    opacity: torch.Tensor,
    rgb: torch.Tensor,
    pixels_xy: torch.Tensor,
    background_rgb: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Composite N screen-space Gaussians at P pixels ``pixels_xy`` (P, 2); returns rgb (P, 3), depth (P,), silhouette (P,).

    Inputs are the fields of :class:`ScreenGaussians` but the bound (means_px (N, 2), conics_px (N, 3), depths_m,
    opacity (N,), rgb (N, 3)).
    """
    in_front = torch.nonzero(depths_m > NEAR_PLANE_M).squeeze(1)
    # Front to back by float32 depth, ties in index order: the order the CPU kernel uses whatever the dtype.
    order = in_front[torch.sort(depths_m[in_front].to(torch.float32), stable=True).indices]
    means_px, conics_px, depths_m = means_px[order], conics_px[order], depths_m[order]
    opacity, rgb = opacity[order], rgb[order]

    dx = pixels_xy[None, :, 0] - means_px[:, None, 0]  # (N, P)
    dy = pixels_xy[None, :, 1] - means_px[:, None, 1]
    a, b, c = (conics_px[:, column, None] for column in range(3))
    mahalanobis_sq = (a * dx + 2.0 * b * dy) * dx + c * dy * dy  # d^T Q d, (N, P)
    alpha = torch.clamp(opacity[:, None] * torch.exp(-0.5 * mahalanobis_sq), max=ALPHA_MAX)
    alpha = torch.where(mahalanobis_sq <= SIGMA_CUTOFF**2, alpha, torch.zeros_like(alpha))

    transmittance_after = torch.cumprod(1.0 - alpha, dim=0)  # T_{i+1} = prod_{j<=i} (1 - alpha_j)
    included = (transmittance_after >= TRANSMITTANCE_MIN).detach()  # a prefix along N: T only decreases
    transmittance_before = torch.cat([torch.ones_like(alpha[:1]), transmittance_after[:-1]], dim=0)
    weights = alpha * transmittance_before * included
    transmittance_final = torch.where(included, 1.0 - alpha, torch.ones_like(alpha)).prod(dim=0)

    colour = weights.T @ rgb + transmittance_final[:, None] * background_rgb
    return colour, weights.T @ depths_m, weights.sum(dim=0)


def composite_reference(
    screen: ScreenGaussians,
    width: int,
    height: int,
    background_rgb: torch.Tensor,
    tile_px: int | None = None,
) -> RenderOutput:
    """Render (height, width) maps of ``screen``; ``background_rgb`` (3,) fills what the Gaussians leave uncovered.

    ``tile_px=None`` evaluates all Gaussians at all pixels in one dense tensor (N x H x W: tests only). With a tile
    size, each tile of pixels composites only the Gaussians whose bounding box overlaps it (exact: the others have
    alpha 0 there) and, under autograd, recomputes its tile in the backward pass (checkpointing) so that memory stays
    bounded; this is the naive torch baseline of the benchmark.
    """
    device, dtype = screen.means_px.device, screen.means_px.dtype
    background_rgb = torch.as_tensor(background_rgb, dtype=dtype, device=device)
    fields = (screen.means_px, screen.conics_px, screen.depths_m, screen.opacity, screen.rgb)
    if tile_px is None:
        ys, xs = torch.meshgrid(
            torch.arange(height, dtype=dtype, device=device), torch.arange(width, dtype=dtype, device=device), indexing="ij"
        )
        colour, depth, silhouette = composite_pixels(*fields, torch.stack([xs, ys], dim=-1).reshape(-1, 2), background_rgb)
        return RenderOutput(colour.reshape(height, width, 3), depth.reshape(height, width), silhouette.reshape(height, width))

    reach = screen.bounds_px.detach()
    u, v = screen.means_px.detach()[:, 0], screen.means_px.detach()[:, 1]
    visible = screen.depths_m.detach() > NEAR_PLANE_M
    rows_rgb, rows_depth, rows_silhouette = [], [], []
    for y0 in range(0, height, tile_px):
        y1 = min(y0 + tile_px, height) - 1
        in_band = torch.nonzero(visible & (v + reach >= y0) & (v - reach <= y1)).squeeze(1)
        tiles_rgb, tiles_depth, tiles_silhouette = [], [], []
        for x0 in range(0, width, tile_px):
            x1 = min(x0 + tile_px, width) - 1
            in_tile = in_band[(u[in_band] + reach[in_band] >= x0) & (u[in_band] - reach[in_band] <= x1)]
            ys, xs = torch.meshgrid(
                torch.arange(y0, y1 + 1, dtype=dtype, device=device),
                torch.arange(x0, x1 + 1, dtype=dtype, device=device),
                indexing="ij",
            )
            pixels_xy = torch.stack([xs, ys], dim=-1).reshape(-1, 2)
            tile_fields = [field[in_tile] for field in fields]
            if torch.is_grad_enabled() and any(field.requires_grad for field in tile_fields):
                colour, depth, silhouette = torch.utils.checkpoint.checkpoint(
                    composite_pixels, *tile_fields, pixels_xy, background_rgb, use_reentrant=False
                )
            else:
                colour, depth, silhouette = composite_pixels(*tile_fields, pixels_xy, background_rgb)
            shape = (y1 + 1 - y0, x1 + 1 - x0)
            tiles_rgb.append(colour.reshape(*shape, 3))
            tiles_depth.append(depth.reshape(shape))
            tiles_silhouette.append(silhouette.reshape(shape))
        rows_rgb.append(torch.cat(tiles_rgb, dim=1))
        rows_depth.append(torch.cat(tiles_depth, dim=1))
        rows_silhouette.append(torch.cat(tiles_silhouette, dim=1))
    return RenderOutput(torch.cat(rows_rgb, dim=0), torch.cat(rows_depth, dim=0), torch.cat(rows_silhouette, dim=0))
