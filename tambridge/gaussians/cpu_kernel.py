"""Numba kernels of the CPU rasteriser: tile binning, forward compositing and its exact backward pass.

Layout. The image is cut into ``TILE_PX`` x ``TILE_PX`` tiles. Each visible Gaussian is listed in every tile its
3-sigma box overlaps, each tile's list in front-to-back order (one global depth sort, then a stable counting sort
by tile). A list entry carries a copy of its Gaussian's packed row, so the passes below read memory in order
instead of jumping around the (N, 8) input; that alone halves their time at 200k Gaussians. Tiles are
independent, so both passes run one tile per thread (``prange``).

Within a tile the Gaussians are *splatted*: each entry visits only the pixels of its 3-sigma box, in list order,
updating that pixel's running transmittance and sums. For the one-pixel Gaussians the mapper creates this costs
~40 pixel updates per entry instead of the 256 of a per-pixel gather over the tile's list, with the same result:
every pixel still sees its Gaussians in depth order. A pixel is marked done when compositing stops there (3DGS
rule: the Gaussian that would bring T below ``TRANSMITTANCE_MIN`` is left out), a tile when all its pixels are.

The backward pass is the 3DGS reverse pass: walking each tile's list back to front, every pixel recovers
``T_i = T_{i+1} / (1 - alpha_i)`` from the final transmittance stored by the forward pass and keeps the sums of
what lies behind the current Gaussian (``acc``), which gives ``dC/dalpha_i = T_i (c_i - acc_i) - T_final bg / (1 - alpha_i)``
(likewise for depth and silhouette; only the dot product of ``acc`` with the pixel's gradients is kept). Gradients are written per list entry, so threads never share a slot, then
summed per Gaussian. All arithmetic is float64.
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
    """Per-tile front-to-back lists of the M visible Gaussians.

    Tile t owns entries ``tile_starts[t]:tile_starts[t + 1]`` of ``entry_rows`` (E, PACKED_COLUMNS), each a copy of
    its Gaussian's packed row. ``order`` (M,) lists the visible Gaussians front to back; the k-th of them owns the
    gradient slots ``slot_starts[k]:slot_starts[k + 1]``, one per tile it is listed in, and entry e writes its
    gradients to slot ``entry_slots[e]``, so that summing a Gaussian's gradients reads consecutive memory.
    """

    entry_rows: np.ndarray
    entry_slots: np.ndarray
    tile_starts: np.ndarray
    tiles_x: int
    order: np.ndarray
    slot_starts: np.ndarray
    gaussian_count: int


@dataclasses.dataclass
class ForwardState:
    """What the backward pass needs per pixel: final transmittance (H, W) float64 and list length used (H, W) int32."""

    transmittance_final: np.ndarray
    contributors: np.ndarray


def depth_order(depths: np.ndarray) -> np.ndarray:
    """Indices sorting ``depths`` (N,) by their float32 values, ties in index order (a stable argsort of float32).

    Positive float32 bit patterns sort like the numbers, so one unique int64 key (depth bits, index) sorts with
    numpy's fast unstable sort, ~5x faster than a stable argsort. Depths must be positive.
    """
    bits = depths.astype(np.float32).view(np.uint32).astype(np.uint64)
    keys = (bits << np.uint64(32)) | np.arange(depths.size, dtype=np.uint64)
    return (np.sort(keys) & np.uint64(0xFFFFFFFF)).astype(np.int64)


@numba.njit(cache=True, inline="always")
def _pixel_box(u, v, radius, x_lo, x_hi, y_lo, y_hi):
    """Inclusive pixel box of the 3-sigma disc at (u, v), clipped to [x_lo, x_hi] x [y_lo, y_hi]."""
    reach = SIGMA_CUTOFF * radius + BOX_SLACK_PX
    # Clamp before rounding: a huge splat (a Gaussian at the near plane) must not overflow the int conversion.
    x0 = max(math.ceil(max(u - reach, x_lo - 1.0)), x_lo)
    x1 = min(math.floor(min(u + reach, x_hi + 1.0)), x_hi)
    y0 = max(math.ceil(max(v - reach, y_lo - 1.0)), y_lo)
    y1 = min(math.floor(min(v + reach, y_hi + 1.0)), y_hi)
    return x0, x1, y0, y1


@numba.njit(cache=True)
def _bin_tiles(packed, order, width, height, tile_px, tiles_x, tiles_y):
    """Counting sort of (Gaussian, tile) entries by tile, stable in depth order.

    Serial: it is memory-bound (a random gather, then scattered appends to the tiles' lists), and a parallel
    version with per-chunk counts cost more CPU time and no less wall time on 2 cores.
    """
    count = order.size
    sorted_rows = np.empty((count, PACKED_COLUMNS))
    tile_boxes = np.empty((count, 4), np.int64)
    slot_starts = np.zeros(count + 1, np.int64)
    tile_starts = np.zeros(tiles_x * tiles_y + 1, np.int64)
    # The one pass that reads the input in random order; alone in its loop, so the loads overlap (2x faster).
    for k in range(count):
        for column in range(PACKED_COLUMNS):
            sorted_rows[k, column] = packed[order[k], column]
    for k in range(count):
        x0, x1, y0, y1 = _pixel_box(sorted_rows[k, U], sorted_rows[k, V], sorted_rows[k, RADIUS], 0, width - 1, 0, height - 1)
        if x0 > x1 or y0 > y1:  # off the image, or between pixel centres
            tx0, tx1, ty0, ty1 = 0, -1, 0, -1
        else:
            tx0, tx1, ty0, ty1 = x0 // tile_px, x1 // tile_px, y0 // tile_px, y1 // tile_px
        tile_boxes[k, 0], tile_boxes[k, 1], tile_boxes[k, 2], tile_boxes[k, 3] = tx0, tx1, ty0, ty1
        slot_starts[k + 1] = slot_starts[k] + (tx1 - tx0 + 1) * (ty1 - ty0 + 1)
        for ty in range(ty0, ty1 + 1):
            for tx in range(tx0, tx1 + 1):
                tile_starts[ty * tiles_x + tx + 1] += 1
    for tile in range(tiles_x * tiles_y):
        tile_starts[tile + 1] += tile_starts[tile]
    cursor = tile_starts[:-1].copy()
    entry_rows = np.empty((tile_starts[-1], PACKED_COLUMNS))
    entry_slots = np.empty(tile_starts[-1], np.int64)
    for k in range(count):
        slot = slot_starts[k]
        for ty in range(tile_boxes[k, 2], tile_boxes[k, 3] + 1):
            for tx in range(tile_boxes[k, 0], tile_boxes[k, 1] + 1):
                entry = cursor[ty * tiles_x + tx]
                cursor[ty * tiles_x + tx] = entry + 1
                for column in range(PACKED_COLUMNS):
                    entry_rows[entry, column] = sorted_rows[k, column]
                entry_slots[entry] = slot
                slot += 1
    return entry_rows, entry_slots, tile_starts, slot_starts


def bin_tiles(packed: np.ndarray, width: int, height: int) -> TileBins:
    """Bin packed Gaussians (N, PACKED_COLUMNS) float64 into tiles, front to back; Gaussians behind the near
    plane or off the image are left out."""
    reach = SIGMA_CUTOFF * packed[:, RADIUS] + BOX_SLACK_PX
    u, v = packed[:, U], packed[:, V]
    # Off-image Gaussians leave here, before the sort: a map is usually much larger than one view.
    visible = np.flatnonzero(
        (packed[:, DEPTH] > NEAR_PLANE_M) & (packed[:, RADIUS] > 0)
        & (u + reach >= 0) & (u - reach <= width - 1) & (v + reach >= 0) & (v - reach <= height - 1)
    )  # fmt: skip
    order = visible[depth_order(packed[visible, DEPTH])]
    tiles_x, tiles_y = -(-width // TILE_PX), -(-height // TILE_PX)
    entry_rows, entry_slots, tile_starts, slot_starts = _bin_tiles(packed, order, width, height, TILE_PX, tiles_x, tiles_y)
    return TileBins(entry_rows, entry_slots, tile_starts, tiles_x, order, slot_starts, packed.shape[0])


@numba.njit(cache=True, inline="always")
def _axis_falloff(centre, lo, hi, half_inv_radius_sq, step_ratio, offsets, distance_sq, falloff):
    """For pixels lo..hi on one axis: offset p - centre, squared offset in radii^2 and ``exp(-offset^2 / 2r^2)``.

    exp(-|d|^2 / 2r^2) = exp(-dx^2 / 2r^2) exp(-dy^2 / 2r^2), so a box needs per-axis factors only, and along an
    axis they follow f_{k+1} = f_k g_k, g_{k+1} = g_k exp(-1 / r^2) (``step_ratio``): three exps per axis.
    """
    offset = lo - centre
    value = math.exp(-half_inv_radius_sq * offset * offset)
    ratio = math.exp(-half_inv_radius_sq * (2.0 * offset + 1.0))
    for k in range(hi - lo + 1):
        offsets[k] = offset + k
        distance_sq[k] = 2.0 * half_inv_radius_sq * offsets[k] * offsets[k]
        falloff[k] = value
        value *= ratio
        ratio *= step_ratio


@numba.njit(parallel=True, cache=True)
def _forward(entry_rows, tile_starts, tiles_x, tile_px, background, out_rgb, out_depth, out_silhouette, out_transmittance, out_contributors):
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
        x_offsets, x_distance_sq, x_falloff = np.empty(tile_w), np.empty(tile_w), np.empty(tile_w)
        y_offsets, y_distance_sq, y_falloff = np.empty(tile_h), np.empty(tile_h), np.empty(tile_h)
        pixels_left = tile_h * tile_w
        start = tile_starts[tile]
        for entry in range(start, tile_starts[tile + 1]):
            if pixels_left == 0:
                break
            row = entry_rows[entry]
            u, v, radius, z, opacity = row[U], row[V], row[RADIUS], row[DEPTH], row[OPACITY]
            red, green, blue = row[RED], row[RED + 1], row[RED + 2]
            half_inv_radius_sq = 0.5 / (radius * radius)
            step_ratio = math.exp(-2.0 * half_inv_radius_sq)
            x0, x1, y0, y1 = _pixel_box(u, v, radius, x_lo, x_hi, y_lo, y_hi)
            _axis_falloff(u, x0, x1, half_inv_radius_sq, step_ratio, x_offsets, x_distance_sq, x_falloff)
            _axis_falloff(v, y0, y1, half_inv_radius_sq, step_ratio, y_offsets, y_distance_sq, y_falloff)
            for ky in range(y1 - y0 + 1):
                ly = y0 - y_lo + ky
                for kx in range(x1 - x0 + 1):
                    lx = x0 - x_lo + kx
                    if done[ly, lx] or x_distance_sq[kx] + y_distance_sq[ky] > _CUTOFF_SQ:
                        continue
                    alpha = min(opacity * x_falloff[kx] * y_falloff[ky], ALPHA_MAX)
                    t = transmittance[ly, lx]
                    t_next = t * (1.0 - alpha)
                    if t_next < TRANSMITTANCE_MIN:
                        done[ly, lx] = True
                        pixels_left -= 1
                        continue
                    weight = alpha * t
                    colour[ly, lx, 0] += weight * red
                    colour[ly, lx, 1] += weight * green
                    colour[ly, lx, 2] += weight * blue
                    depth[ly, lx] += weight * z
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
    bins: TileBins, width: int, height: int, background_rgb: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, ForwardState]:
    """Composite binned Gaussians; returns rgb (H, W, 3), depth (H, W), silhouette (H, W) float64 and the backward state."""
    out_rgb = np.empty((height, width, 3))
    out_depth = np.empty((height, width))
    out_silhouette = np.empty((height, width))
    out_transmittance = np.empty((height, width))
    out_contributors = np.empty((height, width), np.int32)
    _forward(
        bins.entry_rows, bins.tile_starts, bins.tiles_x, TILE_PX, np.asarray(background_rgb, np.float64),
        out_rgb, out_depth, out_silhouette, out_transmittance, out_contributors,
    )
    return out_rgb, out_depth, out_silhouette, ForwardState(out_transmittance, out_contributors)


@numba.njit(parallel=True, cache=True)
def _backward(entry_rows, entry_slots, tile_starts, tiles_x, tile_px, background, transmittance_final, contributors, grad_rgb, grad_depth, grad_silhouette, slot_grads):
    height, width = grad_depth.shape
    for tile in numba.prange(tile_starts.size - 1):
        y_lo = (tile // tiles_x) * tile_px
        x_lo = (tile % tiles_x) * tile_px
        y_hi = min(y_lo + tile_px, height) - 1
        x_hi = min(x_lo + tile_px, width) - 1
        tile_h, tile_w = y_hi - y_lo + 1, x_hi - x_lo + 1
        transmittance = transmittance_final[y_lo : y_hi + 1, x_lo : x_hi + 1].copy()
        used = contributors[y_lo : y_hi + 1, x_lo : x_hi + 1]
        pixel_grads = np.empty((tile_h, tile_w, 5))  # dL/d(red, green, blue, depth, silhouette) of the pixel
        # behind: what lies behind the current Gaussian per unit transmittance in front of it (colour, depth and
        # silhouette), already dotted with the pixel's gradients; it is updated linearly, so one scalar suffices.
        behind = np.zeros((tile_h, tile_w))
        # T_final * dL/dT_final through the background term C += T_final * bg.
        background_term = np.zeros((tile_h, tile_w))
        for ly in range(tile_h):
            for lx in range(tile_w):
                for channel in range(3):
                    pixel_grads[ly, lx, channel] = grad_rgb[y_lo + ly, x_lo + lx, channel]
                    background_term[ly, lx] += background[channel] * grad_rgb[y_lo + ly, x_lo + lx, channel]
                pixel_grads[ly, lx, 3] = grad_depth[y_lo + ly, x_lo + lx]
                pixel_grads[ly, lx, 4] = grad_silhouette[y_lo + ly, x_lo + lx]
                background_term[ly, lx] *= transmittance[ly, lx]
        x_offsets, x_distance_sq, x_falloff = np.empty(tile_w), np.empty(tile_w), np.empty(tile_w)
        y_offsets, y_distance_sq, y_falloff = np.empty(tile_h), np.empty(tile_h), np.empty(tile_h)
        start = tile_starts[tile]
        for position in range(used.max() - 1, -1, -1):
            entry = start + position
            row = entry_rows[entry]
            u, v, radius, z, opacity = row[U], row[V], row[RADIUS], row[DEPTH], row[OPACITY]
            red, green, blue = row[RED], row[RED + 1], row[RED + 2]
            half_inv_radius_sq = 0.5 / (radius * radius)
            step_ratio = math.exp(-2.0 * half_inv_radius_sq)
            x0, x1, y0, y1 = _pixel_box(u, v, radius, x_lo, x_hi, y_lo, y_hi)
            _axis_falloff(u, x0, x1, half_inv_radius_sq, step_ratio, x_offsets, x_distance_sq, x_falloff)
            _axis_falloff(v, y0, y1, half_inv_radius_sq, step_ratio, y_offsets, y_distance_sq, y_falloff)
            grad_u = grad_v = grad_radius = grad_z = grad_opacity = grad_red = grad_green = grad_blue = 0.0
            for ky in range(y1 - y0 + 1):
                ly = y0 - y_lo + ky
                for kx in range(x1 - x0 + 1):
                    lx = x0 - x_lo + kx
                    distance_sq = x_distance_sq[kx] + y_distance_sq[ky]
                    if position >= used[ly, lx] or distance_sq > _CUTOFF_SQ:
                        continue
                    raw_alpha = opacity * x_falloff[kx] * y_falloff[ky]
                    alpha = min(raw_alpha, ALPHA_MAX)
                    inv_one_minus_alpha = 1.0 / (1.0 - alpha)
                    t = transmittance[ly, lx] * inv_one_minus_alpha
                    transmittance[ly, lx] = t
                    weight = alpha * t
                    g_red, g_green, g_blue = pixel_grads[ly, lx, 0], pixel_grads[ly, lx, 1], pixel_grads[ly, lx, 2]
                    g_depth, g_silhouette = pixel_grads[ly, lx, 3], pixel_grads[ly, lx, 4]
                    grad_red += weight * g_red
                    grad_green += weight * g_green
                    grad_blue += weight * g_blue
                    grad_z += weight * g_depth
                    own = red * g_red + green * g_green + blue * g_blue + z * g_depth + g_silhouette
                    grad_alpha = t * (own - behind[ly, lx]) - background_term[ly, lx] * inv_one_minus_alpha
                    behind[ly, lx] += alpha * (own - behind[ly, lx])
                    if raw_alpha > ALPHA_MAX:
                        continue  # clamped: alpha does not depend on the parameters here
                    grad_opacity += grad_alpha * x_falloff[kx] * y_falloff[ky]
                    # alpha = o exp(-q / 2), q = ((px - u)^2 + (py - v)^2) / r^2
                    grad_q = -0.5 * grad_alpha * raw_alpha
                    grad_u -= grad_q * 2.0 * x_offsets[kx] * 2.0 * half_inv_radius_sq
                    grad_v -= grad_q * 2.0 * y_offsets[ky] * 2.0 * half_inv_radius_sq
                    grad_radius -= grad_q * 2.0 * distance_sq / radius
            grad = slot_grads[entry_slots[entry]]  # this entry's own slot: no other thread writes it
            grad[U], grad[V], grad[RADIUS], grad[DEPTH], grad[OPACITY] = grad_u, grad_v, grad_radius, grad_z, grad_opacity
            grad[RED], grad[RED + 1], grad[RED + 2] = grad_red, grad_green, grad_blue


@numba.njit(parallel=True, cache=True)
def _sum_slots(order, slot_starts, slot_grads, grads):
    for k in numba.prange(order.size):
        for column in range(PACKED_COLUMNS):
            total = 0.0
            for slot in range(slot_starts[k], slot_starts[k + 1]):
                total += slot_grads[slot, column]
            grads[order[k], column] = total


def composite_backward(
    bins: TileBins,
    state: ForwardState,
    background_rgb: np.ndarray,
    grad_rgb: np.ndarray,
    grad_depth: np.ndarray,
    grad_silhouette: np.ndarray,
) -> np.ndarray:
    """Gradients (N, PACKED_COLUMNS) float64 of the loss w.r.t. the packed columns, given its gradients w.r.t.
    the rendered rgb (H, W, 3), depth (H, W) and silhouette (H, W), all float64."""
    slot_grads = np.zeros((bins.entry_slots.size, PACKED_COLUMNS))
    _backward(
        bins.entry_rows, bins.entry_slots, bins.tile_starts, bins.tiles_x, TILE_PX, np.asarray(background_rgb, np.float64),
        state.transmittance_final, state.contributors, grad_rgb, grad_depth, grad_silhouette, slot_grads,
    )
    grads = np.zeros((bins.gaussian_count, PACKED_COLUMNS))
    _sum_slots(bins.order, bins.slot_starts, slot_grads, grads)
    return grads
