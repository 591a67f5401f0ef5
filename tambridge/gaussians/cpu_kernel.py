"""Numba kernels of the CPU rasteriser: tile binning, forward compositing and its exact backward pass, and the
projection to screen space with its backward (for renders whose pose is not optimised).

Layout. The image is cut into ``TILE_PX`` x ``TILE_PX`` tiles. Each visible Gaussian is listed in every tile its
box overlaps (the square around the bounding circle of its 3-sigma ellipse), each tile's list in front-to-back
order: a stable counting sort by tile in index order
(parallel over chunks of Gaussians, reading the input in sequence), then a stable radix sort of each tile's list by
depth (parallel over tiles, in cache). A list entry carries a copy of its Gaussian's packed row, so the passes
below read memory in order instead of jumping around the (N, PACKED_COLUMNS) input.
Rows are stored in the dtype of the input (float32 for the mapper's float32 Gaussians, which halves the
memory traffic at no loss: every kernel computes in float64). Tiles are independent, so the tile passes run one
group of tiles per thread, the groups balanced by entry count (:func:`balanced_groups`).

Within a tile the Gaussians are *splatted*: each entry visits only the pixels of its 3-sigma ellipse (the EWA
footprint of :mod:`tambridge.gaussians.model`, cut where ``d^T Q d > SIGMA_CUTOFF^2``; no ``eps2d`` dilation), in
list order, updating that pixel's running transmittance and sums. For the one-pixel Gaussians the mapper creates this costs
~30 pixel updates per entry instead of the 1024 of a per-pixel gather over the tile's list, with the same result:
every pixel still sees its Gaussians in depth order. A pixel is marked done when compositing stops there (3DGS
rule: the Gaussian that would bring T below ``TRANSMITTANCE_MIN`` is left out), a tile when all its pixels are.
Both passes evaluate a Gaussian's footprint with the same helpers (:func:`_footprint`, :func:`_row_span`,
:func:`_row_start`, :func:`_next_row`), so their alphas agree to the bit.

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
import warnings

import numba
import numpy as np

from tambridge.camera import Camera, pinhole_numba
from tambridge.gaussians.model import (
    ALPHA_MAX,
    NEAR_PLANE_M,
    SIGMA_CUTOFF,
    TRANSMITTANCE_MIN,
    conic_scales,
    ewa_terms,
    jacobian_limits,
)

# numba tries TBB first for parallel kernels and warns on every run where only an older TBB is installed; it then
# uses OpenMP, which is what these kernels are tuned for, so the warning tells a user nothing.
warnings.filterwarnings("ignore", message=".*The TBB threading layer requires TBB", category=numba.NumbaWarning)

TILE_PX = 32
"""Tile side, pixels. 32 rather than GPU rasterisers' 16: a Gaussian whose box crosses a tile border is listed (and
its footprint evaluated) once per tile, so larger tiles hold fewer entries, which the binning, both passes and the
gradient sum all scale with."""
BOX_SLACK_PX = 1e-3
"""The pixel box of a Gaussian is widened by this so that rounding never drops a pixel the 3-sigma test keeps."""

# Columns of the packed (N, PACKED_COLUMNS) input: projected mean u, v (px), conic a, b, c (px^-2, the inverse 2D
# covariance [[a, b], [b, c]]), bound (px: radius of the circle around the mean that holds the 3-sigma ellipse),
# depth z (m), opacity in (0, 1), rgb. The backward pass returns gradients in the same columns (0 for the bound).
U, V, CONIC_A, CONIC_B, CONIC_C, BOUND, DEPTH, OPACITY, RED = 0, 1, 2, 3, 4, 5, 6, 7, 8
PACKED_COLUMNS = 11

_CUTOFF_SQ = SIGMA_CUTOFF * SIGMA_CUTOFF


@dataclasses.dataclass
class TileBins:
    """Per-tile front-to-back lists of the visible Gaussians among N.

    Tile t owns entries ``tile_starts[t]:tile_starts[t + 1]`` of ``entry_rows`` (E, PACKED_COLUMNS), each a copy of
    its Gaussian's packed row (dtype of the packed input). For the backward pass, Gaussian i is listed as the entries
    ``slot_entries[slot_starts[i]:slot_starts[i + 1]]`` ((E,) and (N + 1,); none for a culled one), one per tile it
    overlaps: the backward pass writes per-entry gradients in entry order, and each Gaussian gathers its own;
    ``entry_sums`` (E,) int64 names the Gaussian whose gradient each entry sums (its first entry does), -1 for the
    others. All three are None when the bins were made without slots (forward-only renders). The tile passes run one group of tiles
    per thread: group g is tiles ``tile_groups[group_starts[g]:group_starts[g + 1]]`` (see :func:`balanced_groups`).
    """

    entry_rows: np.ndarray
    tile_starts: np.ndarray
    tiles_x: int
    tile_groups: np.ndarray
    group_starts: np.ndarray
    slot_entries: np.ndarray | None
    slot_starts: np.ndarray | None
    entry_sums: np.ndarray | None


@dataclasses.dataclass
class ForwardState:
    """What the backward pass needs per pixel: final transmittance (H, W) float64 and list length used (H, W) int32."""

    transmittance_final: np.ndarray
    contributors: np.ndarray


@numba.njit(cache=True, inline="always")
def _pixel_box(u, v, bound, x_lo, x_hi, y_lo, y_hi):
    """Inclusive pixel box of the disc of radius ``bound`` at (u, v), clipped to [x_lo, x_hi] x [y_lo, y_hi]."""
    reach = bound + BOX_SLACK_PX
    # Clamp before rounding: a huge splat (a Gaussian at the near plane) must not overflow the int conversion.
    x0 = max(math.ceil(max(u - reach, x_lo - 1.0)), x_lo)
    x1 = min(math.floor(min(u + reach, x_hi + 1.0)), x_hi)
    y0 = max(math.ceil(max(v - reach, y_lo - 1.0)), y_lo)
    y1 = min(math.floor(min(v + reach, y_hi + 1.0)), y_hi)
    return x0, x1, y0, y1


@numba.njit(cache=True, inline="always")
def _tile_box(row, width, height):
    """Inclusive tile box (tx0, tx1, ty0, ty1) of a packed row; empty (tx1 < tx0) when the Gaussian is behind the
    near plane, has no extent or touches no pixel centre of the image. NaN fields fail every test, so cull too."""
    u, v, bound, depth = np.float64(row[U]), np.float64(row[V]), np.float64(row[BOUND]), np.float64(row[DEPTH])
    if not (depth > NEAR_PLANE_M and bound > 0.0):
        return 0, -1, 0, -1
    reach = bound + BOX_SLACK_PX
    if not (u + reach >= 0.0 and u - reach <= width - 1.0 and v + reach >= 0.0 and v - reach <= height - 1.0):
        return 0, -1, 0, -1
    x0, x1, y0, y1 = _pixel_box(u, v, bound, 0, width - 1, 0, height - 1)
    if x0 > x1 or y0 > y1:  # between pixel centres
        return 0, -1, 0, -1
    # TILE_PX is a compile-time constant: the divisions become shifts (runtime divisions slow the binning).
    return x0 // TILE_PX, x1 // TILE_PX, y0 // TILE_PX, y1 // TILE_PX


_ewa_terms = numba.njit(cache=True, inline="always")(ewa_terms)


@numba.njit(parallel=True, cache=True)
def _project(means_m, log_radii_m, opacity_logits, rgb, camera_from_world, scalars, packed):
    fx, fy, cx, cy, one = scalars[0], scalars[1], scalars[2], scalars[3], scalars[4]
    x_lo, x_hi, y_lo, y_hi = scalars[5], scalars[6], scalars[7], scalars[8]
    scale_a, scale_b, scale_c, bound_scale = scalars[9], scalars[10], scalars[11], scalars[12]
    m = camera_from_world
    for i in numba.prange(means_m.shape[0]):
        x, y, z = means_m[i, 0], means_m[i, 1], means_m[i, 2]
        camera_x = ((x * m[0, 0] + y * m[0, 1]) + z * m[0, 2]) + m[0, 3]
        camera_y = ((x * m[1, 0] + y * m[1, 1]) + z * m[1, 2]) + m[1, 3]
        depth = ((x * m[2, 0] + y * m[2, 1]) + z * m[2, 2]) + m[2, 3]
        safe_depth = depth if depth > NEAR_PLANE_M else one
        packed[i, U], packed[i, V] = pinhole_numba(camera_x, camera_y, safe_depth, fx, fy, cx, cy)
        xn = min(max(camera_x / safe_depth, x_lo), x_hi)
        yn = min(max(camera_y / safe_depth, y_lo), y_hi)
        radius_over_depth = math.exp(log_radii_m[i]) / safe_depth
        plus_yy, xy, plus_xx, spread = _ewa_terms(xn, yn, radius_over_depth)
        packed[i, CONIC_A] = plus_yy * (scale_a / spread)
        packed[i, CONIC_B] = xy * (scale_b / spread)
        packed[i, CONIC_C] = plus_xx * (scale_c / spread)
        packed[i, BOUND] = bound_scale * math.sqrt(spread)
        packed[i, DEPTH] = depth
        packed[i, OPACITY] = one / (one + math.exp(-opacity_logits[i]))
        for channel in range(3):
            packed[i, RED + channel] = rgb[i, channel]


def project_scalars(camera: Camera, dtype) -> np.ndarray:
    """The camera's numbers that :func:`_project` and :func:`_project_backward` read, as torch casts Python
    scalars: fx, fy, cx, cy, 1, the EWA Jacobian limits, the conic scales and the bound's scale."""
    return np.array([
        camera.fx, camera.fy, camera.cx, camera.cy, 1.0, *jacobian_limits(camera), *conic_scales(camera),
        SIGMA_CUTOFF * max(camera.fx, camera.fy),
    ], dtype)  # fmt: skip


def project(
    means_m: np.ndarray,
    log_radii_m: np.ndarray,
    opacity_logits: np.ndarray,
    rgb: np.ndarray,
    camera_from_world: np.ndarray,
    camera: Camera,
) -> np.ndarray:
    """Packed screen-space rows (N, PACKED_COLUMNS) of N Gaussians in one parallel pass (its backward:
    :func:`project_backward`): the fast twin of :func:`tambridge.gaussians.model.camera_frame_means` and
    :func:`~tambridge.gaussians.model.project_to_screen`.

    means_m (N, 3) world frame, log_radii_m (N,), opacity_logits (N,), rgb (N, 3): all float32 or all float64,
    which is also the dtype of the rows and of the arithmetic. camera_from_world: (4, 4). camera: the pinhole
    intrinsics. The operations are torch's, in its order and dtype, so that the depths (and with them the
    front-to-back order, ties included) and the means are bit-identical to the torch projection's; the conic, bound
    and opacity go through libm's exp and sqrt instead of torch's and may differ in the last bits.
    """
    dtype = means_m.dtype
    packed = np.empty((means_m.shape[0], PACKED_COLUMNS), dtype)
    _project(means_m, log_radii_m, opacity_logits, rgb, camera_from_world.astype(dtype), project_scalars(camera, dtype),
             packed)
    return packed


def project_backward(
    means_m: np.ndarray,
    log_radii_m: np.ndarray,
    opacity_logits: np.ndarray,
    camera_from_world: np.ndarray,
    camera: Camera,
    grad_packed: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gradients of a loss w.r.t. ``means_m`` (N, 3), ``log_radii_m`` (N,) and ``opacity_logits`` (N,) given its
    gradients ``grad_packed`` (N, PACKED_COLUMNS) w.r.t. :func:`project`'s rows (the bound's and the colours' are
    not used: the bound is not differentiated, the colours pass through). The chain rule of
    :func:`tambridge.gaussians.model.project_to_screen` after ``camera_frame_means``, whose autograd is the slow
    twin: a clamped normalised coordinate passes no gradient, nor does the stand-in depth of a Gaussian behind the
    near plane. Inputs as :func:`project`'s; arithmetic in float64, results in the dtype of the means."""
    dtype = means_m.dtype
    count = means_m.shape[0]
    grad_means = np.empty((count, 3), dtype)
    grad_log_radii = np.empty(count, dtype)
    grad_opacity_logits = np.empty(count, dtype)
    _project_backward(means_m, log_radii_m, opacity_logits, np.asarray(camera_from_world, np.float64),
                      project_scalars(camera, np.float64), grad_packed, grad_means, grad_log_radii, grad_opacity_logits)
    return grad_means, grad_log_radii, grad_opacity_logits


@numba.njit(parallel=True, cache=True)
def _project_backward(means_m, log_radii_m, opacity_logits, camera_from_world, scalars, grad_packed, grad_means,
                      grad_log_radii, grad_opacity_logits):
    fx, fy = scalars[0], scalars[1]
    x_lo, x_hi, y_lo, y_hi = scalars[5], scalars[6], scalars[7], scalars[8]
    scale_a, scale_b, scale_c = scalars[9], scalars[10], scalars[11]
    m = camera_from_world
    for i in numba.prange(means_m.shape[0]):
        x, y, z = np.float64(means_m[i, 0]), np.float64(means_m[i, 1]), np.float64(means_m[i, 2])
        camera_x = ((x * m[0, 0] + y * m[0, 1]) + z * m[0, 2]) + m[0, 3]
        camera_y = ((x * m[1, 0] + y * m[1, 1]) + z * m[1, 2]) + m[1, 3]
        depth = ((x * m[2, 0] + y * m[2, 1]) + z * m[2, 2]) + m[2, 3]
        in_front = depth > NEAR_PLANE_M
        inverse_depth = 1.0 / depth if in_front else 1.0
        x_ratio, y_ratio = camera_x * inverse_depth, camera_y * inverse_depth
        xn, yn = min(max(x_ratio, x_lo), x_hi), min(max(y_ratio, y_lo), y_hi)
        radius_over_depth = math.exp(np.float64(log_radii_m[i])) * inverse_depth
        plus_yy, xy, plus_xx, spread = _ewa_terms(xn, yn, radius_over_depth)
        row = grad_packed[i]
        grad_a, grad_b, grad_c = np.float64(row[CONIC_A]), np.float64(row[CONIC_B]), np.float64(row[CONIC_C])
        # conic = (plus_yy, xy, plus_xx) * scales / spread, spread = (r / z)^2 (1 + xn^2 + yn^2)
        grad_spread = -(grad_a * plus_yy * scale_a + grad_b * xy * scale_b + grad_c * plus_xx * scale_c) / (spread * spread)
        grad_plus_yy, grad_xy, grad_plus_xx = grad_a * scale_a / spread, grad_b * scale_b / spread, grad_c * scale_c / spread
        squared = radius_over_depth * radius_over_depth
        grad_radius_over_depth = grad_spread * 2.0 * radius_over_depth * (plus_xx + yn * yn)
        grad_xn = 2.0 * xn * (grad_spread * squared + grad_plus_xx) + grad_xy * yn
        grad_yn = 2.0 * yn * (grad_spread * squared + grad_plus_yy) + grad_xy * xn
        # torch.clamp passes the gradient where the value lies within the limits, ends included
        grad_x_ratio = grad_xn if x_lo <= x_ratio <= x_hi else 0.0
        grad_y_ratio = grad_yn if y_lo <= y_ratio <= y_hi else 0.0
        # u = fx x / z + cx, and x / z, y / z, r / z all divide by the (stand-in) depth
        along_x = grad_x_ratio + np.float64(row[U]) * fx
        along_y = grad_y_ratio + np.float64(row[V]) * fy
        grad_camera_x, grad_camera_y = along_x * inverse_depth, along_y * inverse_depth
        grad_depth = np.float64(row[DEPTH])
        if in_front:
            grad_depth -= (along_x * x_ratio + along_y * y_ratio + grad_radius_over_depth * radius_over_depth) * inverse_depth
        for column in range(3):
            grad_means[i, column] = m[0, column] * grad_camera_x + m[1, column] * grad_camera_y + m[2, column] * grad_depth
        grad_log_radii[i] = grad_radius_over_depth * radius_over_depth
        opacity = 1.0 / (1.0 + math.exp(-np.float64(opacity_logits[i])))
        grad_opacity_logits[i] = np.float64(row[OPACITY]) * opacity * (1.0 - opacity)


@numba.njit(parallel=True, cache=True)
def _count_tiles(packed, width, height, tiles_x, chunk_size, boxes, chunk_tile_counts):
    """Tile box (tx0, tx1, ty0, ty1) of every Gaussian into ``boxes`` (N, 4) (empty when culled, see
    :func:`_tile_box`) and, for each chunk of ``chunk_size`` consecutive Gaussians, its entries per tile into
    ``chunk_tile_counts`` (chunks, tiles), zeroed by the caller."""
    for chunk in numba.prange(chunk_tile_counts.shape[0]):
        counts = chunk_tile_counts[chunk]
        for i in range(chunk * chunk_size, min(packed.shape[0], (chunk + 1) * chunk_size)):
            tx0, tx1, ty0, ty1 = _tile_box(packed[i], width, height)
            boxes[i, 0], boxes[i, 1], boxes[i, 2], boxes[i, 3] = tx0, tx1, ty0, ty1
            for ty in range(ty0, ty1 + 1):
                for tx in range(tx0, tx1 + 1):
                    counts[ty * tiles_x + tx] += 1


@numba.njit(parallel=True, cache=True)
def _scatter_to_tiles(depth_bits, boxes, tiles_x, chunk_size, chunk_cursors, chunk_first_slots, with_slots, tile_keys, slot_starts):
    """Stable counting sort by tile, in index order: Gaussian i's depth key ``depth_bits[i] << 32 | i`` goes to the
    next free place of each tile it overlaps (``boxes`` (N, 4)). Each chunk of ``chunk_size`` Gaussians writes from
    its own cursors (``chunk_cursors`` (chunks, tiles), after those of the chunks before it), so each tile's keys
    come in index order. Only the 8-byte keys move here: scattering whole rows to every tile is slower.

    With ``with_slots``, Gaussian i's entries get slots ``slot_starts[i]:slot_starts[i + 1]``, its chunk's from
    ``chunk_first_slots[chunk]`` on."""
    for chunk in numba.prange(chunk_cursors.shape[0]):
        cursors = chunk_cursors[chunk]
        first, last = chunk * chunk_size, min(depth_bits.size, (chunk + 1) * chunk_size)
        slot = chunk_first_slots[chunk]
        for i in range(first, last):
            tx0, tx1, ty0, ty1 = boxes[i, 0], boxes[i, 1], boxes[i, 2], boxes[i, 3]
            if with_slots:
                slot_starts[i] = slot
                slot += max(tx1 - tx0 + 1, 0) * max(ty1 - ty0 + 1, 0)
            key = (np.int64(depth_bits[i]) << 32) | i
            for ty in range(ty0, ty1 + 1):
                for tx in range(tx0, tx1 + 1):
                    place = cursors[ty * tiles_x + tx]
                    cursors[ty * tiles_x + tx] = place + 1
                    tile_keys[place] = key


RADIX_BITS = 11
"""Digit width of :func:`sort_depth_keys`: three passes cover the 31 bits of a positive float32, and the 2048-bin
histograms stay in L1."""


@numba.njit(cache=True)
def sort_depth_keys(keys):
    """Sort depth keys ``depth_bits << 32 | index`` (n,) int64, which come in ascending index order, in place.

    With the keys in index order, a stable sort by the depth bits alone sorts them whole: an LSD radix sort, one
    pass per ``RADIX_BITS`` digit of the upper word (skipped when every key has the same digit there). The fast
    twin of ``np.sort`` for such keys.
    """
    n = keys.size
    mask = (1 << RADIX_BITS) - 1
    passes = -(-31 // RADIX_BITS)
    histograms = np.zeros((passes, mask + 1), np.int64)
    for k in range(n):
        for digit in range(passes):
            histograms[digit, (keys[k] >> (32 + digit * RADIX_BITS)) & mask] += 1
    source, target = keys, np.empty_like(keys)
    in_place = True
    for digit in range(passes):
        shift = 32 + digit * RADIX_BITS
        histogram = histograms[digit]
        if n == 0 or histogram[(keys[0] >> shift) & mask] == n:
            continue
        total = 0
        for bucket in range(mask + 1):
            total, histogram[bucket] = total + histogram[bucket], total
        for k in range(n):
            key = source[k]
            bucket = (key >> shift) & mask
            target[histogram[bucket]] = key
            histogram[bucket] += 1
        source, target = target, source
        in_place = not in_place
    if not in_place:
        keys[:] = source


@numba.njit(parallel=True, cache=True)
def _sort_tiles(packed, boxes, tile_keys, tile_starts, tiles_x, tile_groups, group_starts, with_slots, slot_starts, entry_rows, slot_entries, entry_sums):
    """Each tile's keys front to back (:func:`sort_depth_keys`), then its Gaussians' rows copied in that order into
    ``entry_rows``; with ``with_slots``, each entry's place goes to its Gaussian's slot for this tile in
    ``slot_entries`` (slots follow the tile box row by row), and ``entry_sums`` gets the Gaussian at its first slot's
    entry, -1 elsewhere."""
    for group in numba.prange(group_starts.size - 1):
        for tile in tile_groups[group_starts[group] : group_starts[group + 1]]:
            start, end = tile_starts[tile], tile_starts[tile + 1]
            keys = tile_keys[start:end]
            sort_depth_keys(keys)
            tx, ty = tile % tiles_x, tile // tiles_x
            for entry in range(start, end):
                # Random reads of the input, but one per entry and independent: the loads overlap.
                i = keys[entry - start] & 0xFFFFFFFF
                for column in range(PACKED_COLUMNS):
                    entry_rows[entry, column] = packed[i, column]
                if with_slots:
                    tx0, tx1, ty0 = boxes[i, 0], boxes[i, 1], boxes[i, 2]
                    slot = (ty - ty0) * (tx1 - tx0 + 1) + tx - tx0
                    slot_entries[slot_starts[i] + slot] = entry
                    entry_sums[entry] = i if slot == 0 else -1


@numba.njit(cache=True)
def balanced_groups(costs, group_count):
    """Items (n,) grouped for ``group_count`` threads so that their summed ``costs`` (n,) are even: the longest
    first, each to the group with the least so far (LPT; no group exceeds another by more than the largest cost).
    Returns ``items`` (n,) and ``group_starts`` (group_count + 1,): group g is ``items[group_starts[g]:group_starts[g + 1]]``.

    numba's ``prange`` splits its range into equal contiguous blocks, one per thread, whatever each item costs; the
    image's tiles differ widely in entries (fewer at the image edges and in empty regions), so the thread with the
    busier half of the image would set the pace.
    """
    loads = np.zeros(group_count)
    group_of = np.empty(costs.size, np.int64)
    for item in np.argsort(-costs, kind="mergesort"):
        group = np.argmin(loads)
        group_of[item] = group
        loads[group] += costs[item]
    group_starts = np.zeros(group_count + 1, np.int64)
    for item in range(costs.size):
        group_starts[group_of[item] + 1] += 1
    group_starts = np.cumsum(group_starts)
    items = np.empty(costs.size, np.int64)
    cursors = group_starts[:-1].copy()
    for item in range(costs.size):
        items[cursors[group_of[item]]] = item
        cursors[group_of[item]] += 1
    return items, group_starts


def bin_tiles(packed: np.ndarray, width: int, height: int, with_slots: bool = True) -> TileBins:
    """Bin packed Gaussians (N, PACKED_COLUMNS), float32 or float64, into tiles, front to back by their float32
    depth (ties in index order); Gaussians behind the near plane or off the image are left out. ``with_slots``:
    also list each Gaussian's entries, which the backward pass needs (``slot_entries``, ``slot_starts``)."""
    count = packed.shape[0]
    if count >= 2**32:
        raise ValueError(f"bin_tiles: {count} Gaussians, the depth keys hold at most 2**32 - 1")
    tiles_x, tiles_y = -(-width // TILE_PX), -(-height // TILE_PX)
    chunk_count = 4 * numba.get_num_threads()
    chunk_size = max(1, -(-count // chunk_count))
    boxes = np.empty((count, 4), np.int32)
    chunk_tile_counts = np.zeros((chunk_count, tiles_x * tiles_y), np.int64)
    _count_tiles(packed, width, height, tiles_x, chunk_size, boxes, chunk_tile_counts)
    tile_starts = np.zeros(tiles_x * tiles_y + 1, np.int64)
    np.cumsum(chunk_tile_counts.sum(axis=0), out=tile_starts[1:])
    chunk_cursors = tile_starts[:-1] + np.cumsum(chunk_tile_counts, axis=0) - chunk_tile_counts
    # Positive float32 bit patterns sort like the numbers (the only depths kept are > NEAR_PLANE_M > 0).
    depth_bits = np.ascontiguousarray(packed[:, DEPTH]).astype(np.float32).view(np.int32)
    entry_count = int(tile_starts[-1])
    tile_keys = np.empty(entry_count, np.int64)
    chunk_entries = chunk_tile_counts.sum(axis=1)
    chunk_first_slots = np.cumsum(chunk_entries) - chunk_entries
    slot_starts = np.empty(count + 1 if with_slots else 0, np.int64)
    _scatter_to_tiles(
        depth_bits, boxes, tiles_x, chunk_size, chunk_cursors, chunk_first_slots, with_slots, tile_keys, slot_starts
    )
    tile_groups, group_starts = balanced_groups(np.diff(tile_starts).astype(np.float64), numba.get_num_threads())
    entry_rows = np.empty((entry_count, PACKED_COLUMNS), packed.dtype)
    slot_entries, entry_sums = (np.empty(entry_count if with_slots else 0, np.int64) for _ in range(2))
    _sort_tiles(
        packed, boxes, tile_keys, tile_starts, tiles_x, tile_groups, group_starts, with_slots, slot_starts,
        entry_rows, slot_entries, entry_sums,
    )
    if not with_slots:
        return TileBins(entry_rows, tile_starts, tiles_x, tile_groups, group_starts, None, None, None)
    slot_starts[count] = entry_count
    return TileBins(entry_rows, tile_starts, tiles_x, tile_groups, group_starts, slot_entries, slot_starts, entry_sums)


@numba.njit(cache=True, inline="always")
def _entry_box(row, x_lo, x_hi, y_lo, y_hi):
    """Pixel box (x0, x1, y0, y1) of a list entry's bounding disc within the tile [x_lo, x_hi] x [y_lo, y_hi]."""
    return _pixel_box(np.float64(row[U]), np.float64(row[V]), np.float64(row[BOUND]), x_lo, x_hi, y_lo, y_hi)


@numba.njit(cache=True, inline="always")
def _footprint(row, x0, y0):
    """A list entry's footprint over its pixel box from corner (x0, y0): the recurrences' start values.

    With ``q(dx, dy) = (a dx + 2 b dy) dx + c dy^2`` (the squared Mahalanobis distance) the falloff is
    ``exp(-q / 2)``. ``q`` is quadratic in dx along a box row, so ``f_{k+1} = f_k g_k``, ``g_{k+1} = g_k exp(-a)``;
    the rows' first-column values and ratios follow in y the same way (``exp(-c)``, ``exp(-b)``): six exps per
    entry, whatever its size. Returns (offset_x, offset_y, column_value, column_ratio, column_step, row_ratio,
    row_ratio_step, row_step): ``column_value`` the falloff at the corner, ``column_ratio`` its ratio to the next
    row's, ``row_ratio`` the falloff's ratio from the corner to its right neighbour.

    The one place, with :func:`_row_span`, :func:`_row_start` and :func:`_next_row`, where the forward and backward
    passes evaluate a Gaussian's shape, so both see bit-identical alphas, which the backward's recovery
    ``T_i = T_{i+1} / (1 - alpha_i)`` relies on. Every falloff in the box (its corners are the smallest) is at least
    ``exp(-SIGMA_CUTOFF^2 kappa)``, kappa the 2D covariance's condition number (the Jacobian clamp bounds it), so
    the recurrences stay far from float64's underflow.
    """
    a, b, c = np.float64(row[CONIC_A]), np.float64(row[CONIC_B]), np.float64(row[CONIC_C])
    offset_x, offset_y = x0 - np.float64(row[U]), y0 - np.float64(row[V])
    column_value = math.exp(-0.5 * ((a * offset_x + 2.0 * b * offset_y) * offset_x + c * offset_y * offset_y))
    column_ratio = math.exp(-0.5 * (c * (2.0 * offset_y + 1.0) + 2.0 * b * offset_x))
    row_ratio = math.exp(-0.5 * (a * (2.0 * offset_x + 1.0) + 2.0 * b * offset_y))
    return offset_x, offset_y, column_value, column_ratio, math.exp(-c), row_ratio, math.exp(-b), math.exp(-a)


@numba.njit(cache=True, inline="always")
def _row_span(row, offset_x, x_count, dy):
    """Box columns ``kx_lo..kx_hi`` of the box row at vertical offset ``dy`` that lie within the cut-off
    ``q(dx, dy) <= SIGMA_CUTOFF^2``.

    The test is the per-pixel one, done from both ends of the row: q is convex along the row, so the pixels that
    pass are one run (empty when kx_lo > kx_hi).
    """
    a, b, c = np.float64(row[CONIC_A]), np.float64(row[CONIC_B]), np.float64(row[CONIC_C])
    linear, constant = 2.0 * b * dy, c * dy * dy
    kx_lo, kx_hi = 0, x_count - 1
    while kx_lo <= kx_hi and (a * (offset_x + kx_lo) + linear) * (offset_x + kx_lo) + constant > _CUTOFF_SQ:
        kx_lo += 1
    while kx_hi >= kx_lo and (a * (offset_x + kx_hi) + linear) * (offset_x + kx_hi) + constant > _CUTOFF_SQ:
        kx_hi -= 1
    return kx_lo, kx_hi


@numba.njit(cache=True, inline="always")
def _row_start(column_value, row_ratio, row_step, kx_lo):
    """Falloff at box column ``kx_lo`` of a row and its ratio to the next column, from the row's first column."""
    value, ratio = column_value, row_ratio
    for _ in range(kx_lo):
        value *= ratio
        ratio *= row_step
    return value, ratio


@numba.njit(cache=True, inline="always")
def _next_row(column_value, column_ratio, column_step, row_ratio, row_ratio_step):
    """The recurrences of :func:`_footprint` one box row down."""
    return column_value * column_ratio, column_ratio * column_step, row_ratio * row_ratio_step


@numba.njit(cache=True, inline="always")
def _tile_pixels(tile, tiles_x, tile_px, width, height):
    """Pixel bounds (x_lo, x_hi, y_lo, y_hi), inclusive, of tile number ``tile`` (row-major, ``tiles_x`` a row)."""
    y_lo = (tile // tiles_x) * tile_px
    x_lo = (tile % tiles_x) * tile_px
    return x_lo, min(x_lo + tile_px, width) - 1, y_lo, min(y_lo + tile_px, height) - 1


# Columns of the forward pass's per-pixel state.
_PIXEL_T, _PIXEL_RED, _PIXEL_DEPTH, _PIXEL_SILHOUETTE = 0, 1, 4, 5


@numba.njit(parallel=True, cache=True)
def _forward(entry_rows, tile_starts, tile_groups, group_starts, tiles_x, tile_px, background, out_rgb, out_depth, out_silhouette, out_transmittance, out_contributors):
    height, width = out_depth.shape
    for group in numba.prange(group_starts.size - 1):
        for tile in tile_groups[group_starts[group] : group_starts[group + 1]]:
            x_lo, x_hi, y_lo, y_hi = _tile_pixels(tile, tiles_x, tile_px, width, height)
            tile_h, tile_w = y_hi - y_lo + 1, x_hi - x_lo + 1
            # One array for what a pixel update reads and writes (one address per update instead of five):
            # transmittance, then the sums of colour, depth and silhouette.
            pixels = np.zeros((tile_h, tile_w, 6))
            pixels[:, :, _PIXEL_T] = 1.0
            contributors = np.zeros((tile_h, tile_w), np.int32)
            done = np.zeros((tile_h, tile_w), np.bool_)
            pixels_left = tile_h * tile_w
            start = tile_starts[tile]
            for entry in range(start, tile_starts[tile + 1]):
                if pixels_left == 0:
                    break
                row = entry_rows[entry]
                x0, x1, y0, y1 = _entry_box(row, x_lo, x_hi, y_lo, y_hi)
                offset_x, offset_y, column_value, column_ratio, column_step, row_ratio, row_ratio_step, row_step = _footprint(row, x0, y0)
                opacity, z = np.float64(row[OPACITY]), np.float64(row[DEPTH])
                red, green, blue = np.float64(row[RED]), np.float64(row[RED + 1]), np.float64(row[RED + 2])
                for ky in range(y1 - y0 + 1):
                    ly = y0 - y_lo + ky
                    kx_lo, kx_hi = _row_span(row, offset_x, x1 - x0 + 1, offset_y + ky)
                    value, ratio = _row_start(column_value, row_ratio, row_step, kx_lo)
                    column_value, column_ratio, row_ratio = _next_row(column_value, column_ratio, column_step, row_ratio, row_ratio_step)
                    for kx in range(kx_lo, kx_hi + 1):
                        falloff = value
                        value *= ratio
                        ratio *= row_step
                        lx = x0 - x_lo + kx
                        if done[ly, lx]:
                            continue
                        raw_alpha = opacity * falloff
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
        bins.entry_rows, bins.tile_starts, bins.tile_groups, bins.group_starts, bins.tiles_x, TILE_PX, np.asarray(background_rgb, np.float64),
        out_rgb, out_depth, out_silhouette, out_transmittance, out_contributors,
    )
    return out_rgb, out_depth, out_silhouette, ForwardState(out_transmittance, out_contributors)


@numba.njit(parallel=True, cache=True)
def _backward(entry_rows, tile_starts, tile_groups, group_starts, tiles_x, tile_px, background, transmittance_final, contributors, grad_rgb, grad_depth, grad_silhouette, entry_grads):
    height, width = grad_depth.shape
    for group in numba.prange(group_starts.size - 1):
        for tile in tile_groups[group_starts[group] : group_starts[group + 1]]:
            x_lo, x_hi, y_lo, y_hi = _tile_pixels(tile, tiles_x, tile_px, width, height)
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
            start, end = tile_starts[tile], tile_starts[tile + 1]
            last_used = used.max()
            entry_grads[start + last_used : end] = 0.0  # behind every pixel's early stop: no gradient
            for position in range(last_used - 1, -1, -1):
                entry = start + position
                row = entry_rows[entry]
                grad = entry_grads[entry]  # this tile's own rows: no other thread writes them
                x0, x1, y0, y1 = _entry_box(row, x_lo, x_hi, y_lo, y_hi)
                offset_x, offset_y, column_value, column_ratio, column_step, row_ratio, row_ratio_step, row_step = _footprint(row, x0, y0)
                a, b, c = np.float64(row[CONIC_A]), np.float64(row[CONIC_B]), np.float64(row[CONIC_C])
                opacity, z = np.float64(row[OPACITY]), np.float64(row[DEPTH])
                red, green, blue = np.float64(row[RED]), np.float64(row[RED + 1]), np.float64(row[RED + 2])
                # alpha = o f with f = exp(-q / 2), q = a dx^2 + 2 b dx dy + c dy^2 and d = p - (u, v), so
                # d alpha / d(o, u, v, a, b, c) = f * (1, o (a dx + b dy), o (b dx + c dy), -o dx^2 / 2, -o dx dy,
                # -o dy^2 / 2): sum grad_alpha * f * (1, dx, dx^2) along a row, then weigh rows by (1, dy, dy^2).
                grad_z = grad_red = grad_green = grad_blue = 0.0
                sum_1 = sum_dy = sum_dy_sq = sum_dx = sum_dx_dy = sum_dx_sq = 0.0
                for ky in range(y1 - y0 + 1):
                    ly = y0 - y_lo + ky
                    dy = offset_y + ky
                    kx_lo, kx_hi = _row_span(row, offset_x, x1 - x0 + 1, dy)
                    value, ratio = _row_start(column_value, row_ratio, row_step, kx_lo)
                    column_value, column_ratio, row_ratio = _next_row(column_value, column_ratio, column_step, row_ratio, row_ratio_step)
                    row_1 = row_dx = row_dx_sq = 0.0
                    for kx in range(kx_lo, kx_hi + 1):
                        falloff = value
                        value *= ratio
                        ratio *= row_step
                        lx = x0 - x_lo + kx
                        if position >= used[ly, lx]:
                            continue
                        raw_alpha = opacity * falloff
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
                        along_x = grad_alpha * falloff
                        dx = offset_x + kx
                        row_1 += along_x
                        row_dx += along_x * dx
                        row_dx_sq += along_x * dx * dx
                    sum_1 += row_1
                    sum_dy += row_1 * dy
                    sum_dy_sq += row_1 * dy * dy
                    sum_dx += row_dx
                    sum_dx_dy += row_dx * dy
                    sum_dx_sq += row_dx_sq
                grad[U] = opacity * (a * sum_dx + b * sum_dy)
                grad[V] = opacity * (b * sum_dx + c * sum_dy)
                grad[CONIC_A] = -0.5 * opacity * sum_dx_sq
                grad[CONIC_B] = -opacity * sum_dx_dy
                grad[CONIC_C] = -0.5 * opacity * sum_dy_sq
                grad[BOUND] = 0.0
                grad[DEPTH], grad[OPACITY] = grad_z, sum_1
                grad[RED], grad[RED + 1], grad[RED + 2] = grad_red, grad_green, grad_blue


@numba.njit(parallel=True, cache=True)
def _sum_entries(entry_sums, slot_starts, slot_entries, entry_grads, grads):
    # In entry order, each Gaussian summed at its first entry (which is ``entry``, read directly): most Gaussians
    # have one entry, so entry_grads is read in sequence, with no chain of dependent lookups before each load.
    for entry in numba.prange(entry_sums.size):
        i = entry_sums[entry]
        if i < 0:
            continue
        first_slot, end_slot = slot_starts[i], slot_starts[i + 1]
        for column in range(PACKED_COLUMNS):
            total = np.float64(entry_grads[entry, column])  # float64 whatever the dtype of grads
            for slot in range(first_slot + 1, end_slot):
                total += entry_grads[slot_entries[slot], column]
            grads[i, column] = total


def composite_backward(
    bins: TileBins,
    state: ForwardState,
    background_rgb: np.ndarray,
    grad_rgb: np.ndarray,
    grad_depth: np.ndarray,
    grad_silhouette: np.ndarray,
    dtype: type = np.float64,
) -> np.ndarray:
    """Gradients (N, PACKED_COLUMNS), column-major, of ``dtype`` (summed in float64, rounded once) of the loss w.r.t.
    the packed columns, given its gradients w.r.t. the rendered rgb (H, W, 3), depth (H, W) and silhouette (H, W), float32 or
    float64 (read as float64)."""
    if bins.slot_entries is None:
        raise ValueError("composite_backward: the bins were made without slots (bin_tiles(..., with_slots=False))")
    entry_grads = np.empty((bins.slot_entries.size, PACKED_COLUMNS))  # _backward writes every row
    _backward(
        bins.entry_rows, bins.tile_starts, bins.tile_groups, bins.group_starts, bins.tiles_x, TILE_PX, np.asarray(background_rgb, np.float64),
        state.transmittance_final, state.contributors, grad_rgb, grad_depth, grad_silhouette, entry_grads,
    )
    # Culled Gaussians keep zeros. Column-major, so that each column is contiguous: autograd's elementwise ops take
    # on the layout of the column views they get, and over strided memory the projection's backward runs ~2x slower.
    grads = np.zeros((bins.slot_starts.size - 1, PACKED_COLUMNS), dtype, order="F")
    _sum_entries(bins.entry_sums, bins.slot_starts, bins.slot_entries, entry_grads, grads)
    return grads
