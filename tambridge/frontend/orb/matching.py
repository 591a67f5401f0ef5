"""Descriptor matching: Hamming distances and the search of projected map points among a frame's keypoints.

The numba kernels are the shipped path; each has a slow, plainly written twin (``*_reference``) that the
tests compare it with. ORB descriptors are 32 bytes, read as four uint64 words for popcounts.
"""

from __future__ import annotations

import dataclasses

import numba
import numpy as np

GRID_CELL_PX = 16


@numba.njit(cache=True, inline="always")
def _popcount64(x: np.uint64) -> int:
    # SWAR popcount (Hacker's Delight, fig. 5-2).
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return int((x * np.uint64(0x0101010101010101)) >> np.uint64(56))


@numba.njit(cache=True, inline="always")
def _hamming(a: np.ndarray, b: np.ndarray) -> int:
    return _popcount64(a[0] ^ b[0]) + _popcount64(a[1] ^ b[1]) + _popcount64(a[2] ^ b[2]) + _popcount64(a[3] ^ b[3])


def as_words(descriptors: np.ndarray) -> np.ndarray:
    """(N, 32) uint8 descriptors viewed as (N, 4) uint64 words (no copy when contiguous)."""
    assert descriptors.ndim == 2 and descriptors.shape[1] == 32 and descriptors.dtype == np.uint8, descriptors.shape
    return np.ascontiguousarray(descriptors).view(np.uint64)


@numba.njit(cache=True, nogil=True)
def _hamming_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    out = np.empty((a.shape[0], b.shape[0]), np.int32)
    for i in range(a.shape[0]):
        for j in range(b.shape[0]):
            out[i, j] = _hamming(a[i], b[j])
    return out


def hamming_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Bit distances between every row of ``a`` (N, 32) and of ``b`` (M, 32), uint8 -> (N, M) int32."""
    return _hamming_matrix(as_words(a), as_words(b))


def hamming_matrix_reference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Slow twin of :func:`hamming_matrix`: unpack bits and count differences."""
    bits_a = np.unpackbits(a, axis=1).astype(np.int32)
    bits_b = np.unpackbits(b, axis=1).astype(np.int32)
    return (bits_a[:, None, :] != bits_b[None, :, :]).sum(axis=2).astype(np.int32)


HAMMING_VALUES = 257
"""Bit distances between two 256-bit descriptors: 0 to 256."""


@numba.njit(cache=True, nogil=True)
def _distinctive_indices(words: np.ndarray, group_start: np.ndarray) -> np.ndarray:
    # Each pair once, and each row's median from a histogram of its distances (they take 257 values): a point seen
    # by hundreds of keyframes in a long session made the sort per row the cost of keyframe point fusion.
    groups = group_start.shape[0] - 1
    chosen = np.empty(groups, np.int64)
    largest = 0
    for g in range(groups):
        largest = max(largest, group_start[g + 1] - group_start[g])
    distances = np.empty((largest, largest), np.int32)
    counts = np.empty(HAMMING_VALUES, np.int64)
    for g in range(groups):
        start, n = group_start[g], group_start[g + 1] - group_start[g]
        for i in range(n):
            distances[i, i] = 0
            for j in range(i + 1, n):
                distance = _hamming(words[start + i], words[start + j])
                distances[i, j] = distance
                distances[j, i] = distance
        rank = (n - 1) // 2
        best, best_median = start, HAMMING_VALUES
        for i in range(n):
            counts[:] = 0
            for j in range(n):
                counts[distances[i, j]] += 1
            median, below = 0, counts[0]
            while below <= rank:
                median += 1
                below += counts[median]
            if median < best_median:
                best, best_median = start + i, median
        chosen[g] = best
    return chosen


def distinctive_indices(descriptors: np.ndarray, group_start: np.ndarray) -> np.ndarray:
    """ORB-SLAM's distinctive descriptor: per group of descriptors, the one with the least median Hamming
    distance to the group's others (ties: the first).

    ``descriptors`` (O, 32) uint8 are grouped as rows ``group_start[g]:group_start[g + 1]`` (G + 1,), every group
    non-empty; returns the chosen row per group (G,) int64.
    """
    return _distinctive_indices(as_words(descriptors), np.asarray(group_start, np.int64))


def distinctive_indices_reference(descriptors: np.ndarray, group_start: np.ndarray) -> np.ndarray:
    """Slow twin of :func:`distinctive_indices`, from :func:`hamming_matrix_reference`."""
    chosen = []
    for start, stop in zip(group_start[:-1], group_start[1:]):
        distances = hamming_matrix_reference(descriptors[start:stop], descriptors[start:stop])
        medians = np.sort(distances, axis=1)[:, (stop - start - 1) // 2]
        chosen.append(start + int(np.argmin(medians)))
    return np.array(chosen, np.int64)


@dataclasses.dataclass
class KeypointGrid:
    """Keypoints bucketed in square cells of ``cell_px``: keypoint ``order[start[c]:start[c + 1]]`` lie in cell c."""

    cell_px: int
    columns: int
    rows: int
    start: np.ndarray
    order: np.ndarray


def build_keypoint_grid(keypoints_px: np.ndarray, width: int, height: int, cell_px: int = GRID_CELL_PX) -> KeypointGrid:
    """Index keypoints (N, 2) by grid cell for radius searches."""
    columns = (width + cell_px - 1) // cell_px
    rows = (height + cell_px - 1) // cell_px
    cx = np.clip((keypoints_px[:, 0] // cell_px).astype(np.int64), 0, columns - 1)
    cy = np.clip((keypoints_px[:, 1] // cell_px).astype(np.int64), 0, rows - 1)
    cell = cy * columns + cx
    order = np.argsort(cell, kind="stable").astype(np.int64)
    start = np.searchsorted(cell[order], np.arange(columns * rows + 1)).astype(np.int64)
    return KeypointGrid(cell_px, int(columns), int(rows), start, order)


@numba.njit(cache=True, nogil=True)
def _search_by_projection(
    projected_px, predicted_octaves, radius_px, point_words,
    grid_start, grid_order, cell_px, columns, rows,
    keypoints_px, octaves, keypoint_words, keypoint_taken, max_hamming, ratio,
):
    n_points = projected_px.shape[0]
    match = np.full(n_points, -1, np.int64)
    distance = np.full(n_points, 1 << 30, np.int64)
    for p in range(n_points):
        u, v, r = projected_px[p, 0], projected_px[p, 1], radius_px[p]
        level = predicted_octaves[p]
        x0 = max(0, int((u - r) // cell_px))
        x1 = min(columns - 1, int((u + r) // cell_px))
        y0 = max(0, int((v - r) // cell_px))
        y1 = min(rows - 1, int((v + r) // cell_px))
        best, second, best_index = 1 << 30, 1 << 30, -1
        for cy in range(y0, y1 + 1):
            for cx in range(x0, x1 + 1):
                cell = cy * columns + cx
                for k in range(grid_start[cell], grid_start[cell + 1]):
                    i = grid_order[k]
                    if keypoint_taken[i] or abs(octaves[i] - level) > 1:
                        continue
                    du = keypoints_px[i, 0] - u
                    dv = keypoints_px[i, 1] - v
                    if du * du + dv * dv > r * r:
                        continue
                    d = _hamming(point_words[p], keypoint_words[i])
                    if d < best:
                        second = best
                        best, best_index = d, i
                    elif d < second:
                        second = d
        if best_index >= 0 and best <= max_hamming and best < ratio * second:
            match[p] = best_index
            distance[p] = best
    # One map point per keypoint: the closest descriptor wins.
    owner_distance = np.full(keypoints_px.shape[0], 1 << 30, np.int64)
    owner = np.full(keypoints_px.shape[0], -1, np.int64)
    for p in range(n_points):
        i = match[p]
        if i >= 0 and distance[p] < owner_distance[i]:
            owner_distance[i] = distance[p]
            owner[i] = p
    for p in range(n_points):
        i = match[p]
        if i >= 0 and owner[i] != p:
            match[p] = -1
    return match, distance


def search_by_projection(
    projected_px: np.ndarray,
    predicted_octaves: np.ndarray,
    radius_px: np.ndarray,
    point_descriptors: np.ndarray,
    grid: KeypointGrid,
    keypoints_px: np.ndarray,
    octaves: np.ndarray,
    keypoint_descriptors: np.ndarray,
    keypoint_taken: np.ndarray | None = None,
    max_hamming: int = 100,
    ratio: float = 0.8,
) -> tuple[np.ndarray, np.ndarray]:
    """Match map points projected at ``projected_px`` (P, 2) to keypoints within ``radius_px`` (P,).

    A keypoint qualifies if its octave is within one of the point's predicted octave (P,) and it is not
    ``keypoint_taken`` (N,) bool; the best descriptor must be within ``max_hamming`` bits and below ``ratio``
    times the second best (Lowe's test); a keypoint claimed by several points keeps the closest one.
    Returns ``(keypoint index per point (P,), -1 for none; Hamming distance (P,))``.
    """
    n_points = len(projected_px)
    assert projected_px.shape == (n_points, 2) and radius_px.shape == (n_points,), (projected_px.shape, radius_px.shape)
    taken = np.zeros(len(keypoints_px), np.bool_) if keypoint_taken is None else keypoint_taken
    return _search_by_projection(
        np.ascontiguousarray(projected_px, np.float64), np.ascontiguousarray(predicted_octaves, np.int64),
        np.ascontiguousarray(radius_px, np.float64), as_words(point_descriptors),
        grid.start, grid.order, grid.cell_px, grid.columns, grid.rows,
        np.ascontiguousarray(keypoints_px, np.float64), np.ascontiguousarray(octaves, np.int64),
        as_words(keypoint_descriptors), taken, max_hamming, ratio,
    )


def search_by_projection_reference(
    projected_px, predicted_octaves, radius_px, point_descriptors, keypoints_px, octaves, keypoint_descriptors,
    keypoint_taken=None, max_hamming=100, ratio=0.8,
) -> tuple[np.ndarray, np.ndarray]:
    """Slow twin of :func:`search_by_projection`: every point against every keypoint, no grid."""
    distances = hamming_matrix_reference(point_descriptors, keypoint_descriptors)
    taken = np.zeros(len(keypoints_px), bool) if keypoint_taken is None else keypoint_taken
    match = np.full(len(projected_px), -1, np.int64)
    distance = np.full(len(projected_px), 1 << 30, np.int64)
    for p in range(len(projected_px)):
        candidates = []
        for i in range(len(keypoints_px)):
            near = np.sum((keypoints_px[i] - projected_px[p]) ** 2) <= radius_px[p] ** 2
            if near and not taken[i] and abs(octaves[i] - predicted_octaves[p]) <= 1:
                candidates.append((distances[p, i], i))
        candidates.sort()
        if candidates:
            second = candidates[1][0] if len(candidates) > 1 else 1 << 30
            if candidates[0][0] <= max_hamming and candidates[0][0] < ratio * second:
                match[p], distance[p] = candidates[0][1], candidates[0][0]
    for i in set(match[match >= 0].tolist()):
        claimants = np.flatnonzero(match == i)
        winner = claimants[np.argmin(distance[claimants])]
        match[claimants[claimants != winner]] = -1
    return match, distance


@numba.njit(cache=True, nogil=True)
def _nearest_two(query_words, train_words):
    n = query_words.shape[0]
    best_index = np.full(n, -1, np.int64)
    best = np.full(n, 1 << 30, np.int64)
    second = np.full(n, 1 << 30, np.int64)
    for i in range(n):
        for j in range(train_words.shape[0]):
            d = _hamming(query_words[i], train_words[j])
            if d < best[i]:
                second[i] = best[i]
                best[i], best_index[i] = d, j
            elif d < second[i]:
                second[i] = d
    return best_index, best, second


def match_descriptors(
    query: np.ndarray, train: np.ndarray, max_hamming: int = 100, ratio: float = 0.8
) -> tuple[np.ndarray, np.ndarray]:
    """Brute-force matches of ``query`` (N, 32) to ``train`` (M, 32) with Lowe's ratio test, one per train row.

    Returns index pairs ``(query_indices (K,), train_indices (K,))``; used where no pose prior exists
    (relocalisation, loop verification).
    """
    if len(query) == 0 or len(train) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    best, best_distance, second = _nearest_two(as_words(query), as_words(train))
    good = np.flatnonzero((best_distance <= max_hamming) & (best_distance < ratio * second))
    # One query per train descriptor: keep the closest.
    order = good[np.lexsort((best_distance[good], best[good]))]
    first = np.concatenate([[True], best[order][1:] != best[order][:-1]]) if len(order) else np.zeros(0, bool)
    chosen = order[first]
    return chosen.astype(np.int64), best[chosen].astype(np.int64)


def match_descriptors_reference(query: np.ndarray, train: np.ndarray, max_hamming: int = 100, ratio: float = 0.8):
    """Slow twin of :func:`match_descriptors`: the full distance matrix, then the same tests."""
    distances = hamming_matrix_reference(query, train)
    pairs = {}
    for i, row in enumerate(distances):
        order = np.argsort(row, kind="stable")
        best, second = row[order[0]], row[order[1]]
        if best <= max_hamming and best < ratio * second:
            j = int(order[0])
            if j not in pairs or best < pairs[j][1] or (best == pairs[j][1] and i < pairs[j][0]):
                pairs[j] = (i, best)
    chosen = sorted((i, j) for j, (i, _) in pairs.items())
    return np.array([i for i, _ in chosen], np.int64), np.array([j for _, j in chosen], np.int64)
