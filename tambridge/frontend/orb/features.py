"""ORB keypoints spread over the image, with depth, colour and the 3D point each one sees.

cv2's ORB keeps the strongest corners of each pyramid level, which bunch up on a few textured objects. As
ORB-SLAM does, we ask cv2 for several times the wanted count at a low FAST threshold, then keep the best
corners per grid cell and level (each level gets its share of the budget, geometric in the scale factor),
so that tracking sees the whole image. Descriptors are computed only for the kept keypoints.
"""

from __future__ import annotations

import dataclasses

import cv2
import numba
import numpy as np

from tambridge.camera import Camera
from tambridge.frontend.orb.config import OrbFrontendConfig

DESCRIPTOR_BYTES = 32
PATCH_SIZE_PX = 31
OVERSAMPLING = 3


@dataclasses.dataclass
class FrameFeatures:
    """Keypoints of one frame, all arrays of length N in the same order.

    ``keypoints_px`` (N, 2) float64 at pyramid level 0; ``octaves`` (N,) int32; ``descriptors`` (N, 32) uint8;
    ``depth_m`` (N,) float64, 0 where the depth image has none; ``points_camera_m`` (N, 3) float64, the
    back-projection with that depth (rows with no depth are zero); ``colours`` (N, 3) uint8 RGB.
    """

    keypoints_px: np.ndarray
    octaves: np.ndarray
    descriptors: np.ndarray
    depth_m: np.ndarray
    points_camera_m: np.ndarray
    colours: np.ndarray

    def __len__(self) -> int:
        return len(self.octaves)

    @property
    def has_depth(self) -> np.ndarray:
        """(N,) bool: the keypoint has a valid depth."""
        return self.depth_m > 0

    @staticmethod
    def empty() -> "FrameFeatures":
        return FrameFeatures(
            np.zeros((0, 2)), np.zeros(0, np.int32), np.zeros((0, DESCRIPTOR_BYTES), np.uint8),
            np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3), np.uint8),
        )


def level_budgets(n_features: int, scale_factor: float, n_levels: int) -> np.ndarray:
    """Keypoints wanted per pyramid level (n_levels,), falling by ``1/scale_factor`` per level (ORB-SLAM)."""
    factor = 1.0 / scale_factor
    first = n_features * (1.0 - factor) / (1.0 - factor**n_levels)
    budgets = np.round(first * factor ** np.arange(n_levels)).astype(int)
    budgets[-1] = max(0, n_features - budgets[:-1].sum())
    return budgets


def bucket_keypoints(
    keypoints_px: np.ndarray,
    octaves: np.ndarray,
    responses: np.ndarray,
    width: int,
    height: int,
    n_features: int,
    scale_factor: float,
    n_levels: int,
    cell_px: int,
) -> np.ndarray:
    """Indices of the keypoints to keep: per level its budget, spread over grid cells of ``cell_px`` at that level.

    Each cell first gets ``ceil(budget / cells)`` of its strongest corners; the level's remaining budget
    goes to the strongest corners left anywhere; a level over budget drops its weakest. (N, 2), (N,), (N,)
    -> (K,) int64, sorted.
    """
    budgets = level_budgets(n_features, scale_factor, n_levels)
    cell_size = cell_px * scale_factor ** octaves.astype(np.float64)
    columns = np.ceil(width / (cell_px * scale_factor ** np.arange(n_levels))).astype(np.int64)
    cell = (keypoints_px[:, 1] // cell_size).astype(np.int64) * columns[octaves] + (keypoints_px[:, 0] // cell_size).astype(np.int64)
    # Group by (level, cell), strongest first inside a group; rank = position inside the group.
    group = octaves.astype(np.int64) * (1 << 32) + cell
    order = np.lexsort((-responses, group))
    sorted_group = group[order]
    starts = np.flatnonzero(np.concatenate([[True], sorted_group[1:] != sorted_group[:-1]]))
    group_start = np.repeat(starts, np.diff(np.append(starts, len(order))))
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order)) - group_start
    keep = []
    for level in range(n_levels):
        on_level = np.flatnonzero(octaves == level)
        if on_level.size == 0 or budgets[level] == 0:
            continue
        cells = columns[level] * int(np.ceil(height / (cell_px * scale_factor**level)))
        quota = int(np.ceil(budgets[level] / cells))
        first = on_level[rank[on_level] < quota]
        rest = on_level[rank[on_level] >= quota]
        if len(first) > budgets[level]:
            first = first[np.argsort(-responses[first], kind="stable")[: budgets[level]]]
        elif len(first) < budgets[level] and len(rest):
            extra = rest[np.argsort(-responses[rest], kind="stable")[: budgets[level] - len(first)]]
            first = np.concatenate([first, extra])
        keep.append(first)
    return np.sort(np.concatenate(keep)) if keep else np.zeros(0, np.int64)


class OrbExtractor:
    """cv2 ORB with grid bucketing; one instance per frontend (it holds the cv2 detector)."""

    def __init__(self, camera: Camera, config: OrbFrontendConfig) -> None:
        self.camera = camera
        self.config = config
        self._orb = cv2.ORB_create(
            nfeatures=OVERSAMPLING * config.n_features,
            scaleFactor=config.scale_factor,
            nlevels=config.n_levels,
            edgeThreshold=config.edge_threshold_px,
            patchSize=PATCH_SIZE_PX,
            fastThreshold=config.fast_threshold,
        )

    def extract(self, rgb: np.ndarray, depth_m: np.ndarray) -> FrameFeatures:
        """Features of an RGB-D frame: ``rgb`` (H, W, 3) uint8, ``depth_m`` (H, W) float32 metres."""
        camera, config = self.camera, self.config
        assert rgb.shape == (camera.height, camera.width, 3), (rgb.shape, camera)
        gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        detected = self._orb.detect(gray, None)
        if not detected:
            return FrameFeatures.empty()
        points = cv2.KeyPoint_convert(detected).astype(np.float64)
        octaves = np.fromiter((k.octave for k in detected), np.int32, len(detected))
        responses = np.fromiter((k.response for k in detected), np.float64, len(detected))
        keep = bucket_keypoints(points, octaves, responses, camera.width, camera.height, config.n_features,
                                config.scale_factor, config.n_levels, config.grid_cell_px)
        kept, descriptors = self._orb.compute(gray, [detected[i] for i in keep])
        if descriptors is None or not kept:
            return FrameFeatures.empty()
        kept_points = cv2.KeyPoint_convert(kept).astype(np.float64)
        if len(kept) == len(keep) and np.array_equal(kept_points, points[keep]):
            # cv2 kept every keypoint, in order (the usual case): no need to read the octaves back one by one.
            octaves = octaves[keep]
        else:
            octaves = np.fromiter((k.octave for k in kept), np.int32, len(kept))
        return self.lift(kept_points, octaves, descriptors, rgb, depth_m)

    def lift(self, keypoints_px: np.ndarray, octaves: np.ndarray, descriptors: np.ndarray, rgb: np.ndarray,
             depth_m: np.ndarray) -> FrameFeatures:
        """:func:`lift_keypoints` with this extractor's camera and depth settings."""
        config = self.config
        return lift_keypoints(keypoints_px, octaves, descriptors, rgb, depth_m, self.camera, config.min_depth_m,
                              config.max_depth_m, config.depth_edge_window_px, config.depth_edge_ratio)


def lift_keypoints(
    keypoints_px: np.ndarray,
    octaves: np.ndarray,
    descriptors: np.ndarray,
    rgb: np.ndarray,
    depth_m: np.ndarray,
    camera: Camera,
    min_depth_m: float,
    max_depth_m: float,
    edge_window_px: int = 0,
    edge_ratio: float = np.inf,
) -> FrameFeatures:
    """Attach depth, colour and camera-frame 3D points to keypoints (N, 2), their depth as
    :func:`keypoint_depths` gives it."""
    columns = np.clip(np.round(keypoints_px[:, 0]).astype(np.int64), 0, camera.width - 1)
    rows = np.clip(np.round(keypoints_px[:, 1]).astype(np.int64), 0, camera.height - 1)
    depth = keypoint_depths(depth_m, rows, columns, min_depth_m, max_depth_m, edge_window_px, edge_ratio)
    points = camera.backproject(keypoints_px, depth)
    return FrameFeatures(keypoints_px, octaves, np.ascontiguousarray(descriptors), depth, points,
                         rgb[rows, columns].copy())


def keypoint_depths(depth_m: np.ndarray, rows: np.ndarray, columns: np.ndarray, min_depth_m: float, max_depth_m: float,
                    edge_window_px: int = 0, edge_ratio: float = np.inf) -> np.ndarray:
    """Depth (N,) float64 metres of the pixels ``(rows, columns)`` (N,) of ``depth_m`` (H, W), 0 for none.

    It counts as none outside [min, max], and (with ``edge_window_px`` > 0) where the depth in the
    ``2 * edge_window_px + 1`` square around the pixel (clipped to the image) has a hole or spans more than
    ``edge_ratio`` times the depth: corners often sit on depth edges, where a pixel of colour-depth
    misregistration puts the point on the wrong surface. A numba kernel (it runs three times a tracked frame);
    :func:`keypoint_depths_reference` is its slow twin.
    """
    return _keypoint_depths_kernel(np.ascontiguousarray(depth_m), np.ascontiguousarray(rows, np.int64),
                                   np.ascontiguousarray(columns, np.int64), float(min_depth_m), float(max_depth_m),
                                   int(edge_window_px), float(edge_ratio))


@numba.njit(cache=True, nogil=True)
def _keypoint_depths_kernel(depth_m, rows, columns, min_depth_m, max_depth_m, window, ratio):
    height, width = depth_m.shape
    out = np.zeros(rows.shape[0])
    for i in range(rows.shape[0]):
        depth = np.float64(depth_m[rows[i], columns[i]])
        if not (np.isfinite(depth) and min_depth_m <= depth <= max_depth_m):
            continue
        if window > 0:
            lowest = highest = depth_m[rows[i], columns[i]]
            hole = False
            for row_offset in range(-window, window + 1):
                row = min(max(rows[i] + row_offset, 0), height - 1)
                for column_offset in range(-window, window + 1):
                    value = depth_m[row, min(max(columns[i] + column_offset, 0), width - 1)]
                    hole |= not value > 0
                    lowest, highest = min(lowest, value), max(highest, value)
            if hole or not highest - lowest <= ratio * depth:
                continue
        out[i] = depth
    return out


def keypoint_depths_reference(depth_m: np.ndarray, rows: np.ndarray, columns: np.ndarray, min_depth_m: float,
                              max_depth_m: float, edge_window_px: int = 0, edge_ratio: float = np.inf) -> np.ndarray:
    """Slow twin of :func:`keypoint_depths`, on whole arrays."""
    height, width = depth_m.shape
    depth = depth_m[rows, columns].astype(np.float64)
    depth[~np.isfinite(depth) | (depth < min_depth_m) | (depth > max_depth_m)] = 0.0
    if edge_window_px > 0:
        offsets = np.arange(-edge_window_px, edge_window_px + 1)
        patch = depth_m[np.clip(rows[:, None, None] + offsets[None, :, None], 0, height - 1),
                        np.clip(columns[:, None, None] + offsets[None, None, :], 0, width - 1)]
        patch = patch.reshape(len(depth), offsets.size ** 2)
        span = patch.max(axis=1) - patch.min(axis=1)
        depth[~(patch > 0).all(axis=1) | ~(span <= edge_ratio * depth)] = 0.0
    return depth
