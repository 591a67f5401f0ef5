"""Numba kernels of the CPU rasteriser: tile binning, forward compositing and its exact backward pass.

Layout. The image is cut into ``TILE_PX`` x ``TILE_PX`` tiles. Each visible Gaussian is listed in every tile its
3-sigma box overlaps, tiles' lists in front-to-back depth order (a global depth argsort, then a stable counting
sort by tile). Tiles are independent, so both passes run one tile per thread (``prange``).

Within a tile the Gaussians are *splatted*: each list entry visits only the pixels of its 3-sigma box, in list
order, updating that pixel's running transmittance and sums. For the one-pixel Gaussians the mapper creates this
costs ~50 pixel updates per entry instead of the 256 per entry of a per-pixel gather, with the same result: every
pixel still sees its Gaussians in depth order. A pixel is marked done when compositing stops there (3DGS rule:
the Gaussian that would bring T below ``TRANSMITTANCE_MIN`` is left out) and a tile stops when all its pixels are.

The backward pass is the 3DGS reverse pass: walking each tile's list back to front, every pixel recovers
``T_i = T_{i+1} / (1 - alpha_i)`` from the final transmittance stored by the forward pass and keeps the sums of
what lies behind the current Gaussian (``acc``), which gives ``dC/dalpha_i = T_i (c_i - acc_i) - T_final bg / (1 - alpha_i)``
(likewise for depth and silhouette). Gradients are written per (tile, Gaussian) list entry, so threads never share
a slot, then summed per Gaussian. All arithmetic is float64; inputs are packed as float64 rows.
"""

from __future__ import annotations

import dataclasses
import math

import numba
import numpy as np

from tambridge.gaussians.model import ALPHA_MAX, NEAR_PLANE_M, SIGMA_CUTOFF, TRANSMITTANCE_MIN

TILE_PX = 16
"""Tile side, pixels."""
BOX_SLACK_PX = 1e-3
"""The pixel box of a Gaussian is widened by this so that rounding never drops a pixel the 3-sigma test keeps."""

# Columns of the packed (N, PACKED_COLUMNS) float64 input: projected mean u, v (px), 2D radius (px), depth z (m),
# opacity in (0, 1), rgb. The backward pass returns gradients in the same columns.
U, V, RADIUS, DEPTH, OPACITY, RED = 0, 1, 2, 3, 4, 5
PACKED_COLUMNS = 8

_CUTOFF_SQ = SIGMA_CUTOFF * SIGMA_CUTOFF


@dataclasses.dataclass
class TileBins:
    """Per-tile depth-ordered lists: tile t holds ``gaussian_ids[tile_starts[t]:tile_starts[t + 1]]`` (int64)."""

    gaussian_ids: np.ndarray
    tile_starts: np.ndarray
    tiles_x: int
    tiles_y: int


@dataclasses.dataclass
class ForwardState:
    """What the backward pass needs per pixel: final transmittance (H, W) float64 and list length used (H, W) int32."""

    transmittance_final: np.ndarray
    contributors: np.ndarray


@numba.njit(cache=True, inline="always")
def _pixel_box(row, x_lo, x_hi, y_lo, y_hi):
    """Inclusive pixel box of a packed Gaussian's 3-sigma disc, clipped to [x_lo, x_hi] x [y_lo, y_hi]."""
    reach = SIGMA_CUTOFF * row[RADIUS] + BOX_SLACK_PX
    x0 = max(math.ceil(row[U] - reach), x_lo)
    x1 = min(math.floor(row[U] + reach), x_hi)
    y0 = max(math.ceil(row[V] - reach), y_lo)
    y1 = min(math.floor(row[V] + reach), y_hi)
    return x0, x1, y0, y1


@numba.njit(cache=True)
def _bin_tiles(packed, depth_order, width, height, tile_px, tiles_x, tiles_y):
    counts = np.zeros(tiles_x * tiles_y + 1, np.int64)
    for i in depth_order:
        x0, x1, y0, y1 = _pixel_box(packed[i], 0, width - 1, 0, height - 1)
        if x0 > x1 or y0 > y1:
            continue
        for ty in range(y0 // tile_px, y1 // tile_px + 1):
            for tx in range(x0 // tile_px, x1 // tile_px + 1):
                counts[ty * tiles_x + tx + 1] += 1
    tile_starts = np.cumsum(counts)
    cursor = tile_starts[:-1].copy()
    gaussian_ids = np.empty(tile_starts[-1], np.int64)
    for i in depth_order:
        x0, x1, y0, y1 = _pixel_box(packed[i], 0, width - 1, 0, height - 1)
        if x0 > x1 or y0 > y1:
            continue
        for ty in range(y0 // tile_px, y1 // tile_px + 1):
            for tx in range(x0 // tile_px, x1 // tile_px + 1):
                tile = ty * tiles_x + tx
                gaussian_ids[cursor[tile]] = i
                cursor[tile] += 1
    return gaussian_ids, tile_starts


def bin_tiles(packed: np.ndarray, width: int, height: int, tile_px: int = TILE_PX) -> TileBins:
    """Bin packed Gaussians (N, PACKED_COLUMNS) into tiles, front to back; Gaussians behind the near plane or
    off the image are left out."""
    visible = np.flatnonzero((packed[:, DEPTH] > NEAR_PLANE_M) & (packed[:, RADIUS] > 0))
    depth_order = visible[np.argsort(packed[visible, DEPTH], kind="stable")]
    tiles_x, tiles_y = -(-width // tile_px), -(-height // tile_px)
    gaussian_ids, tile_starts = _bin_tiles(packed, depth_order, width, height, tile_px, tiles_x, tiles_y)
    return TileBins(gaussian_ids, tile_starts, tiles_x, tiles_y)


@numba.njit(parallel=True, cache=True)
def _forward(packed, gaussian_ids, tile_starts, tiles_x, tile_px, background, out_rgb, out_depth, out_silhouette, out_transmittance, out_contributors):
    height, width = out_depth.shape
    for tile in numba.prange(tile_starts.size - 1):
        y_lo = (tile // tiles_x) * tile_px
        x_lo = (tile % tiles_x) * tile_px
        y_hi = min(y_lo + tile_px, height) - 1
        x_hi = min(x_lo + tile_px, width) - 1
        tile_h, tile_w = y_hi - y_lo + 1, x_hi - x_lo + 1
        transmittance = np.ones((tile_h, tile_w))
        colour = np.zeros((tile_h, tile_w, 3))
        depth = np.zeros((tile_h, tile_w))
        silhouette = np.zeros((tile_h, tile_w))
        contributors = np.zeros((tile_h, tile_w), np.int32)
        done = np.zeros((tile_h, tile_w), np.bool_)
        pixels_left = tile_h * tile_w
        start = tile_starts[tile]
        for entry in range(start, tile_starts[tile + 1]):
            if pixels_left == 0:
                break
            row = packed[gaussian_ids[entry]]
            radius_sq = row[RADIUS] * row[RADIUS]
            x0, x1, y0, y1 = _pixel_box(row, x_lo, x_hi, y_lo, y_hi)
            for py in range(y0, y1 + 1):
                dy = py - row[V]
                ly = py - y_lo
                for px in range(x0, x1 + 1):
                    lx = px - x_lo
                    if done[ly, lx]:
                        continue
                    dx = px - row[U]
                    distance_sq = (dx * dx + dy * dy) / radius_sq
                    if distance_sq > _CUTOFF_SQ:
                        continue
                    alpha = min(row[OPACITY] * math.exp(-0.5 * distance_sq), ALPHA_MAX)
                    t = transmittance[ly, lx]
                    t_next = t * (1.0 - alpha)
                    if t_next < TRANSMITTANCE_MIN:
                        done[ly, lx] = True
                        pixels_left -= 1
                        continue
                    weight = alpha * t
                    for channel in range(3):
                        colour[ly, lx, channel] += weight * row[RED + channel]
                    depth[ly, lx] += weight * row[DEPTH]
                    silhouette[ly, lx] += weight
                    transmittance[ly, lx] = t_next
                    contributors[ly, lx] = entry - start + 1
        for ly in range(tile_h):
            for lx in range(tile_w):
                for channel in range(3):
                    out_rgb[y_lo + ly, x_lo + lx, channel] = colour[ly, lx, channel] + transmittance[ly, lx] * background[channel]
                out_depth[y_lo + ly, x_lo + lx] = depth[ly, lx]
                out_silhouette[y_lo + ly, x_lo + lx] = silhouette[ly, lx]
                out_transmittance[y_lo + ly, x_lo + lx] = transmittance[ly, lx]
                out_contributors[y_lo + ly, x_lo + lx] = contributors[ly, lx]


def composite_forward(
    packed: np.ndarray, bins: TileBins, width: int, height: int, background_rgb: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, ForwardState]:
    """Composite binned Gaussians; returns rgb (H, W, 3), depth (H, W), silhouette (H, W) float64 and the backward state."""
    out_rgb = np.empty((height, width, 3))
    out_depth = np.empty((height, width))
    out_silhouette = np.empty((height, width))
    out_transmittance = np.empty((height, width))
    out_contributors = np.empty((height, width), np.int32)
    _forward(
        packed, bins.gaussian_ids, bins.tile_starts, bins.tiles_x, TILE_PX, np.asarray(background_rgb, np.float64),
        out_rgb, out_depth, out_silhouette, out_transmittance, out_contributors,
    )
    return out_rgb, out_depth, out_silhouette, ForwardState(out_transmittance, out_contributors)


@numba.njit(parallel=True, cache=True)
def _backward(packed, gaussian_ids, tile_starts, tiles_x, tile_px, background, transmittance_final, contributors, grad_rgb, grad_depth, grad_silhouette, entry_grads):
    height, width = grad_depth.shape
    for tile in numba.prange(tile_starts.size - 1):
        y_lo = (tile // tiles_x) * tile_px
        x_lo = (tile % tiles_x) * tile_px
        y_hi = min(y_lo + tile_px, height) - 1
        x_hi = min(x_lo + tile_px, width) - 1
        tile_h, tile_w = y_hi - y_lo + 1, x_hi - x_lo + 1
        transmittance = transmittance_final[y_lo : y_hi + 1, x_lo : x_hi + 1].copy()
        used = contributors[y_lo : y_hi + 1, x_lo : x_hi + 1]
        acc_colour = np.zeros((tile_h, tile_w, 3))
        acc_depth = np.zeros((tile_h, tile_w))
        acc_silhouette = np.zeros((tile_h, tile_w))
        # Gradient of the loss through the background term T_final * bg, per pixel.
        background_grad = np.zeros((tile_h, tile_w))
        for ly in range(tile_h):
            for lx in range(tile_w):
                for channel in range(3):
                    background_grad[ly, lx] += background[channel] * grad_rgb[y_lo + ly, x_lo + lx, channel]
        start = tile_starts[tile]
        for position in range(used.max() - 1, -1, -1):
            entry = start + position
            row = packed[gaussian_ids[entry]]
            radius_sq = row[RADIUS] * row[RADIUS]
            grad = entry_grads[entry]  # this entry's own row: no other thread writes it
            x0, x1, y0, y1 = _pixel_box(row, x_lo, x_hi, y_lo, y_hi)
            for py in range(y0, y1 + 1):
                dy = py - row[V]
                ly = py - y_lo
                for px in range(x0, x1 + 1):
                    lx = px - x_lo
                    if position >= used[ly, lx]:
                        continue
                    dx = px - row[U]
                    distance_sq = (dx * dx + dy * dy) / radius_sq
                    if distance_sq > _CUTOFF_SQ:
                        continue
                    falloff = math.exp(-0.5 * distance_sq)
                    raw_alpha = row[OPACITY] * falloff
                    alpha = min(raw_alpha, ALPHA_MAX)
                    t = transmittance[ly, lx] / (1.0 - alpha)
                    transmittance[ly, lx] = t
                    weight = alpha * t
                    grad_alpha = 0.0
                    for channel in range(3):
                        pixel_grad = grad_rgb[py, px, channel]
                        grad[RED + channel] += weight * pixel_grad
                        grad_alpha += (row[RED + channel] - acc_colour[ly, lx, channel]) * pixel_grad
                        acc_colour[ly, lx, channel] = alpha * row[RED + channel] + (1.0 - alpha) * acc_colour[ly, lx, channel]
                    grad[DEPTH] += weight * grad_depth[py, px]
                    grad_alpha += (row[DEPTH] - acc_depth[ly, lx]) * grad_depth[py, px]
                    grad_alpha += (1.0 - acc_silhouette[ly, lx]) * grad_silhouette[py, px]
                    grad_alpha = t * grad_alpha - transmittance_final[py, px] / (1.0 - alpha) * background_grad[ly, lx]
                    acc_depth[ly, lx] = alpha * row[DEPTH] + (1.0 - alpha) * acc_depth[ly, lx]
                    acc_silhouette[ly, lx] = alpha + (1.0 - alpha) * acc_silhouette[ly, lx]
                    if raw_alpha > ALPHA_MAX:
                        continue  # clamped: alpha does not depend on the parameters here
                    grad[OPACITY] += grad_alpha * falloff
                    # alpha = o exp(-q / 2), q = (dx^2 + dy^2) / r^2 with dx = px - u
                    grad_q = -0.5 * grad_alpha * raw_alpha
                    grad[U] -= grad_q * 2.0 * dx / radius_sq
                    grad[V] -= grad_q * 2.0 * dy / radius_sq
                    grad[RADIUS] -= grad_q * 2.0 * distance_sq / row[RADIUS]


@numba.njit(cache=True)
def _sum_entries(gaussian_ids, entry_grads, grads):
    for entry in range(gaussian_ids.size):
        grads[gaussian_ids[entry]] += entry_grads[entry]


def composite_backward(
    packed: np.ndarray,
    bins: TileBins,
    state: ForwardState,
    background_rgb: np.ndarray,
    grad_rgb: np.ndarray,
    grad_depth: np.ndarray,
    grad_silhouette: np.ndarray,
) -> np.ndarray:
    """Gradients (N, PACKED_COLUMNS) float64 of the loss w.r.t. the packed columns, given its gradients w.r.t.
    the rendered rgb (H, W, 3), depth (H, W) and silhouette (H, W), all float64."""
    entry_grads = np.zeros((bins.gaussian_ids.size, PACKED_COLUMNS))
    _backward(
        packed, bins.gaussian_ids, bins.tile_starts, bins.tiles_x, TILE_PX, np.asarray(background_rgb, np.float64),
        state.transmittance_final, state.contributors, grad_rgb, grad_depth, grad_silhouette, entry_grads,
    )
    grads = np.zeros_like(packed)
    _sum_entries(bins.gaussian_ids, entry_grads, grads)
    return grads
