"""Numba kernels of the CPU rasteriser: tile binning, forward compositing and its exact backward pass, and (for
renders that need no gradients) the projection to screen space.

Layout. The image is cut into ``TILE_PX`` x ``TILE_PX`` tiles. Each visible Gaussian is listed in every tile its
3-sigma box overlaps, each tile's list in front-to-back order (one global sort of unique int64 depth keys, then a
stable counting sort by tile, parallel over chunks of the depth order). A list entry carries a copy of its
Gaussian's packed row, so the passes below read memory in order instead of jumping around the (N, 8) input; that
alone halves their time at 200k Gaussians. Rows are stored in the dtype of the input (float32 for the mapper's
float32 Gaussians, which halves the memory traffic at no loss: every kernel computes in float64). Tiles are
independent, so both passes run one tile per thread (``prange``).

Within a tile the Gaussians are *splatted*: each entry visits only the pixels of its 3-sigma disc, in list order,
updating that pixel's running transmittance and sums. For the one-pixel Gaussians the mapper creates this costs
~30 pixel updates per entry instead of the 1024 of a per-pixel gather over the tile's list, with the same result:
every pixel still sees its Gaussians in depth order. A pixel is marked done when compositing stops there (3DGS
rule: the Gaussian that would bring T below ``TRANSMITTANCE_MIN`` is left out), a tile when all its pixels are.
Both passes evaluate a Gaussian's footprint with the same helpers (:func:`_footprint`, :func:`_row_span`), so
their alphas agree to the bit.

The backward pass is the 3DGS reverse pass: walking each tile's list back to front, every pixel recovers
``T_i = T_{i+1} / (1 - alpha_i)`` from the final transmittance stored by the forward pass and keeps the sums of
what lies behind the current Gaussian (``acc``), which gives ``dC/dalpha_i = T_i (c_i - acc_i) - T_final bg / (1 - alpha_i)``
(likewise for depth and silhouette; only the dot product of ``acc`` with the pixel's gradients is kept).
Gradients are written per list entry, in entry order (each tile's rows are its thread's own, written in
sequence), then each Gaussian gathers and sums its entries. All arithmetic is float64.
"""

from __future__ import annotations

import dataclasses
import math

import numba
import numpy as np

from tambridge.gaussians.model import ALPHA_MAX, NEAR_PLANE_M, SIGMA_CUTOFF, TRANSMITTANCE_MIN

TILE_PX = 32
"""Tile side, pixels. 32 rather than GPU rasterisers' 16: a Gaussian whose box crosses a tile border is listed (and
its footprint evaluated) once per tile, and at 640x480 with 200k one-pixel Gaussians 32 px tiles hold 24 % fewer
entries (1.3 instead of 1.7 per Gaussian), which the binning, both passes and the gradient sum all scale with."""
BOX_SLACK_PX = 1e-3
"""The pixel box of a Gaussian is widened by this so that rounding never drops a pixel the 3-sigma test keeps."""

# Columns of the packed (N, PACKED_COLUMNS) float64 input: projected mean u, v (px), 2D radius (px), depth z (m),
# opacity in (0, 1), rgb. The backward pass returns gradients in the same columns.
U, V, RADIUS, DEPTH, OPACITY, RED = 0, 1, 2, 3, 4, 5
PACKED_COLUMNS = 8

_CUTOFF_SQ = SIGMA_CUTOFF * SIGMA_CUTOFF


@dataclasses.dataclass
class TileBins:
    """Per-tile front-to-back lists of the visible Gaussians among N.

    Tile t owns entries ``tile_starts[t]:tile_starts[t + 1]`` of ``entry_rows`` (E, PACKED_COLUMNS), each a copy of
    its Gaussian's packed row (dtype of the packed input). ``order`` (M,) lists the visible Gaussians front to back;
    the k-th of them is listed as the entries ``slot_entries[slot_starts[k]:slot_starts[k + 1]]`` ((E,) and
    (M + 1,)), one per tile it overlaps: the backward pass writes per-entry gradients in entry order, and each
    Gaussian gathers its own.
    """

    entry_rows: np.ndarray
    slot_entries: np.ndarray
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


@numba.njit(cache=True, inline="always")
def _tile_box(row, width, height, tile_px):
    """Inclusive tile box (tx0, tx1, ty0, ty1) of a packed row; empty (tx1 < tx0) when the Gaussian is behind the
    near plane, has no radius or touches no pixel centre of the image. NaN fields fail every test, so cull too."""
    u, v, radius, depth = np.float64(row[U]), np.float64(row[V]), np.float64(row[RADIUS]), np.float64(row[DEPTH])
    if not (depth > NEAR_PLANE_M and radius > 0.0):
        return 0, -1, 0, -1
    reach = SIGMA_CUTOFF * radius + BOX_SLACK_PX
    if not (u + reach >= 0.0 and u - reach <= width - 1.0 and v + reach >= 0.0 and v - reach <= height - 1.0):
        return 0, -1, 0, -1
    x0, x1, y0, y1 = _pixel_box(u, v, radius, 0, width - 1, 0, height - 1)
    if x0 > x1 or y0 > y1:  # between pixel centres
        return 0, -1, 0, -1
    return x0 // tile_px, x1 // tile_px, y0 // tile_px, y1 // tile_px


@numba.njit(parallel=True, cache=True)
def _project(means_m, log_radii_m, opacity_logits, rgb, camera_from_world, scalars, packed):
    fx, fy, cx, cy, focal, one = scalars[0], scalars[1], scalars[2], scalars[3], scalars[4], scalars[5]
    m = camera_from_world
    for i in numba.prange(means_m.shape[0]):
        x, y, z = means_m[i, 0], means_m[i, 1], means_m[i, 2]
        camera_x = ((x * m[0, 0] + y * m[0, 1]) + z * m[0, 2]) + m[0, 3]
        camera_y = ((x * m[1, 0] + y * m[1, 1]) + z * m[1, 2]) + m[1, 3]
        depth = ((x * m[2, 0] + y * m[2, 1]) + z * m[2, 2]) + m[2, 3]
        safe_depth = depth if depth > NEAR_PLANE_M else one
        packed[i, U] = fx * camera_x / safe_depth + cx
        packed[i, V] = fy * camera_y / safe_depth + cy
        packed[i, RADIUS] = focal * math.exp(log_radii_m[i]) / safe_depth
        packed[i, DEPTH] = depth
        packed[i, OPACITY] = one / (one + math.exp(-opacity_logits[i]))
        for channel in range(3):
            packed[i, RED + channel] = rgb[i, channel]


def project(
    means_m: np.ndarray,
    log_radii_m: np.ndarray,
    opacity_logits: np.ndarray,
    rgb: np.ndarray,
    camera_from_world: np.ndarray,
    intrinsics: tuple[float, float, float, float],
) -> np.ndarray:
    """Packed screen-space rows (N, PACKED_COLUMNS) of N Gaussians in one parallel pass, for renders that need
    no gradients: the fast twin of :func:`tambridge.gaussians.model.camera_frame_means` and
    :func:`~tambridge.gaussians.model.project_to_screen`.

    means_m (N, 3) world frame, log_radii_m (N,), opacity_logits (N,), rgb (N, 3): all float32 or all float64,
    which is also the dtype of the rows and of the arithmetic. camera_from_world: (4, 4). intrinsics: (fx, fy, cx,
    cy) pixels. The operations are torch's, in its order and dtype, so that the depths (and with them the
    front-to-back order, ties included) and the means are bit-identical to the torch projection's; the radius and
    opacity go through libm's exp instead of torch's and may differ in the last bit.
    """
    dtype = means_m.dtype
    fx, fy, cx, cy = intrinsics
    scalars = np.array([fx, fy, cx, cy, 0.5 * (fx + fy), 1.0], dtype)  # Python scalars as torch casts them
    packed = np.empty((means_m.shape[0], PACKED_COLUMNS), dtype)
    _project(means_m, log_radii_m, opacity_logits, rgb, camera_from_world.astype(dtype), scalars, packed)
    return packed


_CULLED = np.iinfo(np.int64).max
"""Depth key of a culled Gaussian: sorts after every visible one."""


@numba.njit(parallel=True, cache=True)
def _depth_keys(packed, depth_bits, width, height, tile_px, keys):
    """Depth key ``depth_bits << 32 | index`` of every Gaussian (N,), ``_CULLED`` if it is culled; the keys are
    unique, so sorting them gives the front-to-back order with ties in index order."""
    for i in numba.prange(packed.shape[0]):
        tx0, tx1, _, _ = _tile_box(packed[i], width, height, tile_px)
        keys[i] = (np.int64(depth_bits[i]) << 32) | i if tx0 <= tx1 else _CULLED


@numba.njit(parallel=True, cache=True)
def _fill_tiles(packed, sorted_keys, visible_count, width, height, tile_px, tiles_x, tiles_y, chunk_count):
    """Stable parallel counting sort by tile of the visible Gaussians, taken in depth order (``sorted_keys``).

    The depth order is cut into chunks; each chunk counts its entries per tile, prefix sums give each chunk its own
    write cursor in every tile after those of the chunks in front of it, so every tile list stays front to back.
    Returns entry_rows, slot_entries, tile_starts, order (M,) (the visible Gaussians front to back) and
    slot_starts (M + 1,) (the k-th of them is listed as entries ``slot_entries[slot_starts[k]:slot_starts[k + 1]]``).
    """
    tile_count = tiles_x * tiles_y
    chunk_size = -(-visible_count // chunk_count)
    order = np.empty(visible_count, np.int64)
    sorted_rows = np.empty((visible_count, PACKED_COLUMNS), packed.dtype)
    sorted_boxes = np.empty((visible_count, 4), np.int32)  # recomputed: cheaper than a second random read
    chunk_tile_counts = np.zeros((chunk_count, tile_count), np.int64)
    slot_starts = np.empty(visible_count + 1, np.int64)
    for chunk in numba.prange(chunk_count):
        first, last = chunk * chunk_size, min(visible_count, (chunk + 1) * chunk_size)
        # The one loop that reads the input in random order; alone in its loop, so the loads overlap.
        for k in range(first, last):
            i = sorted_keys[k] & 0xFFFFFFFF
            order[k] = i
            for column in range(PACKED_COLUMNS):
                sorted_rows[k, column] = packed[i, column]
        counts = chunk_tile_counts[chunk]
        for k in range(first, last):
            # Box bounds in locals: numba assumes any array store may alias, so loop bounds read back from
            # sorted_boxes would be reloaded after every count update.
            tx0, tx1, ty0, ty1 = _tile_box(sorted_rows[k], width, height, tile_px)
            sorted_boxes[k, 0], sorted_boxes[k, 1], sorted_boxes[k, 2], sorted_boxes[k, 3] = tx0, tx1, ty0, ty1
            slot_starts[k + 1] = (tx1 - tx0 + 1) * (ty1 - ty0 + 1)
            for ty in range(ty0, ty1 + 1):
                for tx in range(tx0, tx1 + 1):
                    counts[ty * tiles_x + tx] += 1
    slot_starts[0] = 0
    for k in range(visible_count):
        slot_starts[k + 1] += slot_starts[k]
    tile_starts = np.empty(tile_count + 1, np.int64)
    chunk_cursors = np.empty((chunk_count, tile_count), np.int64)
    total = 0
    for tile in range(tile_count):
        tile_starts[tile] = total
        for chunk in range(chunk_count):
            chunk_cursors[chunk, tile] = total
            total += chunk_tile_counts[chunk, tile]
    tile_starts[tile_count] = total
    entry_rows = np.empty((total, PACKED_COLUMNS), packed.dtype)
    slot_entries = np.empty(total, np.int64)
    for chunk in numba.prange(chunk_count):
        cursors = chunk_cursors[chunk]
        row = np.empty(PACKED_COLUMNS, entry_rows.dtype)  # in locals for the same reason
        for k in range(chunk * chunk_size, min(visible_count, (chunk + 1) * chunk_size)):
            slot = slot_starts[k]
            tx0, tx1, ty0, ty1 = sorted_boxes[k, 0], sorted_boxes[k, 1], sorted_boxes[k, 2], sorted_boxes[k, 3]
            for column in range(PACKED_COLUMNS):
                row[column] = sorted_rows[k, column]
            for ty in range(ty0, ty1 + 1):
                for tx in range(tx0, tx1 + 1):
                    entry = cursors[ty * tiles_x + tx]
                    cursors[ty * tiles_x + tx] = entry + 1
                    for column in range(PACKED_COLUMNS):
                        entry_rows[entry, column] = row[column]
                    slot_entries[slot] = entry
                    slot += 1
    return entry_rows, slot_entries, tile_starts, order, slot_starts


def bin_tiles(packed: np.ndarray, width: int, height: int) -> TileBins:
    """Bin packed Gaussians (N, PACKED_COLUMNS), float32 or float64, into tiles, front to back by their float32
    depth (ties in index order); Gaussians behind the near plane or off the image are left out."""
    count = packed.shape[0]
    if count >= 2**32:
        raise ValueError(f"bin_tiles: {count} Gaussians, the depth keys hold at most 2**32 - 1")
    # Positive float32 bit patterns sort like the numbers (the only depths kept are > NEAR_PLANE_M > 0).
    depth_bits = np.ascontiguousarray(packed[:, DEPTH]).astype(np.float32).view(np.int32)
    tiles_x, tiles_y = -(-width // TILE_PX), -(-height // TILE_PX)
    keys = np.empty(count, np.int64)
    _depth_keys(packed, depth_bits, width, height, TILE_PX, keys)
    keys.sort()  # numpy's vectorised sort: ~2x numba's, and unique keys make stability moot
    visible_count = int(np.searchsorted(keys, _CULLED))
    entry_rows, slot_entries, tile_starts, order, slot_starts = _fill_tiles(
        packed, keys, visible_count, width, height, TILE_PX, tiles_x, tiles_y, 4 * numba.get_num_threads()
    )
    return TileBins(entry_rows, slot_entries, tile_starts, tiles_x, order, slot_starts, count)


# Rows of the per-axis footprint buffers (3, tile side) filled by _footprint.
OFFSET, DISTANCE_SQ, FALLOFF = 0, 1, 2


@numba.njit(cache=True, inline="always")
def _axis_falloff(offset, count, half_inv_radius_sq, step_ratio, value, axis):
    """For the ``count`` pixels k = 0.. of one axis of a box whose first pixel lies ``offset`` from the centre:
    ``axis[OFFSET, k]`` = offset + k, ``axis[DISTANCE_SQ, k]`` = (offset + k)^2 / r^2 and ``axis[FALLOFF, k]`` =
    ``value`` * exp(-((offset + k)^2 - offset^2) / 2r^2).

    exp(-|d|^2 / 2r^2) = exp(-dx^2 / 2r^2) exp(-dy^2 / 2r^2), so a box needs per-axis factors only, and along an
    axis they follow f_{k+1} = f_k g_k, g_{k+1} = g_k exp(-1 / r^2) (``step_ratio``): one exp per axis for g_0.
    """
    ratio = math.exp(-half_inv_radius_sq * (2.0 * offset + 1.0))
    for k in range(count):
        axis[OFFSET, k] = offset + k
        axis[DISTANCE_SQ, k] = 2.0 * half_inv_radius_sq * axis[OFFSET, k] * axis[OFFSET, k]
        axis[FALLOFF, k] = value
        value *= ratio
        ratio *= step_ratio


@numba.njit(cache=True, inline="always")
def _entry_box(row, x_lo, x_hi, y_lo, y_hi):
    """Pixel box (x0, x1, y0, y1) of a list entry's 3-sigma disc within the tile [x_lo, x_hi] x [y_lo, y_hi]."""
    return _pixel_box(np.float64(row[U]), np.float64(row[V]), np.float64(row[RADIUS]), x_lo, x_hi, y_lo, y_hi)


@numba.njit(cache=True, inline="always")
def _footprint(row, x0, x1, y0, y1, x_axis, y_axis):
    """Fill the per-axis footprint buffers (3, >= box side) of a list entry over its pixel box; returns 1 / (2 r^2).

    The one place where the forward and backward passes evaluate a Gaussian's shape (with :func:`_row_span` for its
    cut-off; the alpha at box pixel (kx, ky) is then ``opacity * x_axis[FALLOFF, kx] * y_axis[FALLOFF, ky]``), so
    both see bit-identical alphas, which the backward's recovery ``T_i = T_{i+1} / (1 - alpha_i)`` relies on.
    """
    radius = np.float64(row[RADIUS])
    half_inv_radius_sq = 0.5 / (radius * radius)
    step_ratio = math.exp(-2.0 * half_inv_radius_sq)
    offset_x, offset_y = x0 - np.float64(row[U]), y0 - np.float64(row[V])
    # Only products x * y of the factors are ever used, so the box corner's exp(-|d|^2 / 2r^2) goes whole into the
    # y factors and the x factors start at 1: four exps per entry instead of five.
    corner = math.exp(-half_inv_radius_sq * (offset_x * offset_x + offset_y * offset_y))
    _axis_falloff(offset_x, x1 - x0 + 1, half_inv_radius_sq, step_ratio, 1.0, x_axis)
    _axis_falloff(offset_y, y1 - y0 + 1, half_inv_radius_sq, step_ratio, corner, y_axis)
    return half_inv_radius_sq


@numba.njit(cache=True, inline="always")
def _row_span(x_axis, x_count, y_distance_sq):
    """Box columns ``kx_lo..kx_hi`` of one box row that lie within the 3-sigma cut-off ``dx^2 + dy^2 <= 9 r^2``.

    The test is the per-pixel one, in the same floating-point expression, done from both ends of the row: the
    squared offsets are convex along the row, so the pixels that pass are one run (empty when kx_lo > kx_hi).
    """
    kx_lo, kx_hi = 0, x_count - 1
    while kx_lo <= kx_hi and x_axis[DISTANCE_SQ, kx_lo] + y_distance_sq > _CUTOFF_SQ:
        kx_lo += 1
    while kx_hi >= kx_lo and x_axis[DISTANCE_SQ, kx_hi] + y_distance_sq > _CUTOFF_SQ:
        kx_hi -= 1
    return kx_lo, kx_hi


# Columns of the forward pass's per-pixel state.
_PIXEL_T, _PIXEL_RED, _PIXEL_DEPTH, _PIXEL_SILHOUETTE = 0, 1, 4, 5


@numba.njit(parallel=True, cache=True)
def _forward(entry_rows, tile_starts, tiles_x, tile_px, background, out_rgb, out_depth, out_silhouette, out_transmittance, out_contributors):
    height, width = out_depth.shape
    for tile in numba.prange(tile_starts.size - 1):
        y_lo = (tile // tiles_x) * tile_px
        x_lo = (tile % tiles_x) * tile_px
        y_hi = min(y_lo + tile_px, height) - 1
        x_hi = min(x_lo + tile_px, width) - 1
        tile_h, tile_w = y_hi - y_lo + 1, x_hi - x_lo + 1
        # One array for what a pixel update reads and writes (one address per update instead of five, -10% time):
        # transmittance, then the sums of colour, depth and silhouette.
        pixels = np.zeros((tile_h, tile_w, 6))
        pixels[:, :, _PIXEL_T] = 1.0
        contributors = np.zeros((tile_h, tile_w), np.int32)
        done = np.zeros((tile_h, tile_w), np.bool_)
        x_axis, y_axis = np.empty((3, tile_w)), np.empty((3, tile_h))
        pixels_left = tile_h * tile_w
        start = tile_starts[tile]
        for entry in range(start, tile_starts[tile + 1]):
            if pixels_left == 0:
                break
            row = entry_rows[entry]
            x0, x1, y0, y1 = _entry_box(row, x_lo, x_hi, y_lo, y_hi)
            _footprint(row, x0, x1, y0, y1, x_axis, y_axis)
            opacity, z = np.float64(row[OPACITY]), np.float64(row[DEPTH])
            red, green, blue = np.float64(row[RED]), np.float64(row[RED + 1]), np.float64(row[RED + 2])
            for ky in range(y1 - y0 + 1):
                ly = y0 - y_lo + ky
                kx_lo, kx_hi = _row_span(x_axis, x1 - x0 + 1, y_axis[DISTANCE_SQ, ky])
                for kx in range(kx_lo, kx_hi + 1):
                    lx = x0 - x_lo + kx
                    if done[ly, lx]:
                        continue
                    raw_alpha = opacity * x_axis[FALLOFF, kx] * y_axis[FALLOFF, ky]
                    alpha = min(raw_alpha, ALPHA_MAX)
                    pixel = pixels[ly, lx]
                    t = pixel[_PIXEL_T]
                    t_next = t * (1.0 - alpha)
                    if t_next < TRANSMITTANCE_MIN:
                        done[ly, lx] = True
                        pixels_left -= 1
                        continue
                    weight = alpha * t
                    pixel[_PIXEL_RED] += weight * red
                    pixel[_PIXEL_RED + 1] += weight * green
                    pixel[_PIXEL_RED + 2] += weight * blue
                    pixel[_PIXEL_DEPTH] += weight * z
                    pixel[_PIXEL_SILHOUETTE] += weight
                    pixel[_PIXEL_T] = t_next
                    contributors[ly, lx] = entry - start + 1
        for ly in range(tile_h):
            for lx in range(tile_w):
                pixel = pixels[ly, lx]
                for channel in range(3):
                    out_rgb[y_lo + ly, x_lo + lx, channel] = pixel[_PIXEL_RED + channel] + pixel[_PIXEL_T] * background[channel]
                out_depth[y_lo + ly, x_lo + lx] = pixel[_PIXEL_DEPTH]
                out_silhouette[y_lo + ly, x_lo + lx] = pixel[_PIXEL_SILHOUETTE]
                out_transmittance[y_lo + ly, x_lo + lx] = pixel[_PIXEL_T]
                out_contributors[y_lo + ly, x_lo + lx] = contributors[ly, lx]


def composite_forward(
    bins: TileBins, width: int, height: int, background_rgb: np.ndarray, dtype: type = np.float64
) -> tuple[np.ndarray, np.ndarray, np.ndarray, ForwardState]:
    """Composite binned Gaussians; returns rgb (H, W, 3), depth (H, W), silhouette (H, W) of ``dtype`` (computed in
    float64, rounded once when stored) and the backward state."""
    out_rgb = np.empty((height, width, 3), dtype)
    out_depth = np.empty((height, width), dtype)
    out_silhouette = np.empty((height, width), dtype)
    out_transmittance = np.empty((height, width))
    out_contributors = np.empty((height, width), np.int32)
    _forward(
        bins.entry_rows, bins.tile_starts, bins.tiles_x, TILE_PX, np.asarray(background_rgb, np.float64),
        out_rgb, out_depth, out_silhouette, out_transmittance, out_contributors,
    )
    return out_rgb, out_depth, out_silhouette, ForwardState(out_transmittance, out_contributors)


@numba.njit(parallel=True, cache=True)
def _backward(entry_rows, tile_starts, tiles_x, tile_px, background, transmittance_final, contributors, grad_rgb, grad_depth, grad_silhouette, entry_grads):
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
        x_axis, y_axis = np.empty((3, tile_w)), np.empty((3, tile_h))
        start, end = tile_starts[tile], tile_starts[tile + 1]
        last_used = used.max()
        entry_grads[start + last_used : end] = 0.0  # behind every pixel's early stop: no gradient
        for position in range(last_used - 1, -1, -1):
            entry = start + position
            row = entry_rows[entry]
            grad = entry_grads[entry]  # this tile's own rows: no other thread writes them
            x0, x1, y0, y1 = _entry_box(row, x_lo, x_hi, y_lo, y_hi)
            half_inv_radius_sq = _footprint(row, x0, x1, y0, y1, x_axis, y_axis)
            radius, opacity, z = np.float64(row[RADIUS]), np.float64(row[OPACITY]), np.float64(row[DEPTH])
            red, green, blue = np.float64(row[RED]), np.float64(row[RED + 1]), np.float64(row[RED + 2])
            # d alpha / d(o, u, v, r) = alpha * (1 / o, dx / r^2, dy / r^2, q / r) with q = (dx^2 + dy^2) / r^2 and
            # alpha = o fx fy: sum grad_alpha * fx * (1, dx, dx^2 / r^2) along a row, then weigh rows by fy.
            grad_z = grad_red = grad_green = grad_blue = 0.0
            sum_opacity = sum_u = sum_v = sum_radius = 0.0
            for ky in range(y1 - y0 + 1):
                ly = y0 - y_lo + ky
                kx_lo, kx_hi = _row_span(x_axis, x1 - x0 + 1, y_axis[DISTANCE_SQ, ky])
                row_falloff = row_offset = row_distance_sq = 0.0
                for kx in range(kx_lo, kx_hi + 1):
                    lx = x0 - x_lo + kx
                    if position >= used[ly, lx]:
                        continue
                    raw_alpha = opacity * x_axis[FALLOFF, kx] * y_axis[FALLOFF, ky]
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
                    along_x = grad_alpha * x_axis[FALLOFF, kx]
                    row_falloff += along_x
                    row_offset += along_x * x_axis[OFFSET, kx]
                    row_distance_sq += along_x * x_axis[DISTANCE_SQ, kx]
                falloff_y = y_axis[FALLOFF, ky]
                sum_opacity += falloff_y * row_falloff
                sum_u += falloff_y * row_offset
                sum_v += falloff_y * y_axis[OFFSET, ky] * row_falloff
                sum_radius += falloff_y * (row_distance_sq + y_axis[DISTANCE_SQ, ky] * row_falloff)
            grad[U] = 2.0 * half_inv_radius_sq * opacity * sum_u
            grad[V] = 2.0 * half_inv_radius_sq * opacity * sum_v
            grad[RADIUS] = opacity * sum_radius / radius
            grad[DEPTH], grad[OPACITY] = grad_z, sum_opacity
            grad[RED], grad[RED + 1], grad[RED + 2] = grad_red, grad_green, grad_blue


@numba.njit(parallel=True, cache=True)
def _sum_entries(order, slot_starts, slot_entries, entry_grads, grads):
    for k in numba.prange(order.size):
        for column in range(PACKED_COLUMNS):
            total = 0.0  # float64 whatever the dtype of grads
            for slot in range(slot_starts[k], slot_starts[k + 1]):
                total += entry_grads[slot_entries[slot], column]
            grads[order[k], column] = total


def composite_backward(
    bins: TileBins,
    state: ForwardState,
    background_rgb: np.ndarray,
    grad_rgb: np.ndarray,
    grad_depth: np.ndarray,
    grad_silhouette: np.ndarray,
    dtype: type = np.float64,
) -> np.ndarray:
    """Gradients (N, PACKED_COLUMNS) of ``dtype`` (summed in float64, rounded once) of the loss w.r.t. the packed
    columns, given its gradients w.r.t. the rendered rgb (H, W, 3), depth (H, W) and silhouette (H, W), float32 or
    float64 (read as float64)."""
    entry_grads = np.empty((bins.slot_entries.size, PACKED_COLUMNS))  # _backward writes every row
    _backward(
        bins.entry_rows, bins.tile_starts, bins.tiles_x, TILE_PX, np.asarray(background_rgb, np.float64),
        state.transmittance_final, state.contributors, grad_rgb, grad_depth, grad_silhouette, entry_grads,
    )
    grads = np.zeros((bins.gaussian_count, PACKED_COLUMNS), dtype)  # culled Gaussians keep zeros
    _sum_entries(bins.order, bins.slot_starts, bins.slot_entries, entry_grads, grads)
    return grads
