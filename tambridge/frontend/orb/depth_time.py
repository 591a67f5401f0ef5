"""The depth image moved to its colour image's time, for sensors that take the two at different times.

TUM's Kinect gives each depth image its own stamp, up to 20 ms from its colour image's; the tracker solves for the
pose at the colour time. Under the constant-velocity prior the camera moves by ``colour_from_depth``
(:func:`colour_from_depth_motion`) between the two. :func:`depth_at_colour_time` then gives, for each pixel, the
depth that the surface seen there in the colour image had at the colour time: a pixel ``u`` of the output looks up
its source in the depth image at ``u - f(u)``, where ``f(u)`` is the image motion of the depth pixel at ``u`` (one
fixed-point step of the inverse warp, exact where the flow is locally constant), and takes that depth pixel's
point's z after ``colour_from_depth``. No holes open, as a forward warp would leave them; pixels whose source
falls outside the image or has no depth get none (0).
"""

from __future__ import annotations

import numba
import numpy as np

from tambridge.camera import pinhole, pinhole_numba, pinhole_ray, pinhole_ray_numba
from tambridge.frontend.orb.reprojection import MIN_DEPTH_M
from tambridge.geometry import exp_se3, log_se3


def colour_from_depth_motion(current_from_previous: np.ndarray, frame_interval_s: float, depth_delay_s: float) -> np.ndarray:
    """The camera at its colour time from the camera at its depth time, (4, 4), when it moves by
    ``current_from_previous`` (4, 4) over ``frame_interval_s`` at constant velocity (twist scaled in se(3));
    ``depth_delay_s`` is ``t_depth - t_colour``."""
    fraction = -depth_delay_s / frame_interval_s
    return exp_se3(fraction * log_se3(current_from_previous))


@numba.njit(cache=True, nogil=True)
def _depth_at_colour_time_kernel(depth_m, rotation, translation, fx, fy, cx, cy):
    height, width = depth_m.shape
    # Each column's and row's ray once (pinhole_ray's arithmetic), not two divisions a pixel twice over.
    ray_x, ray_y = np.empty(width), np.empty(height)
    for column in range(width):
        ray_x[column] = pinhole_ray_numba(float(column), 0.0, fx, fy, cx, cy)[0]
    for row in range(height):
        ray_y[row] = pinhole_ray_numba(0.0, float(row), fx, fy, cx, cy)[1]
    out = np.zeros((height, width), np.float32)
    for row in range(height):
        for column in range(width):
            z = depth_m[row, column]
            if not z > 0:
                continue
            px, py = ray_x[column] * z, ray_y[row] * z
            moved_x = rotation[0, 0] * px + rotation[0, 1] * py + rotation[0, 2] * z + translation[0]
            moved_y = rotation[1, 0] * px + rotation[1, 1] * py + rotation[1, 2] * z + translation[1]
            moved_z = rotation[2, 0] * px + rotation[2, 1] * py + rotation[2, 2] * z + translation[2]
            if not moved_z > MIN_DEPTH_M:
                continue
            u, v = pinhole_numba(moved_x, moved_y, moved_z, fx, fy, cx, cy)
            source_column = int(np.floor(2.0 * column - u + 0.5))
            source_row = int(np.floor(2.0 * row - v + 0.5))
            if source_column < 0 or source_row < 0 or source_column >= width or source_row >= height:
                continue
            source_z = depth_m[source_row, source_column]
            if not source_z > 0:
                continue
            out[row, column] = (rotation[2, 0] * ray_x[source_column] * source_z
                                + rotation[2, 1] * ray_y[source_row] * source_z
                                + rotation[2, 2] * source_z + translation[2])
    return out


def depth_at_colour_time(depth_m: np.ndarray, K: np.ndarray, colour_from_depth: np.ndarray) -> np.ndarray:
    """Depth (H, W) float32 metres, 0 = none, as seen at the colour time (see the module docstring): a numba kernel;
    :func:`depth_at_colour_time_reference` is its slow twin."""
    return _depth_at_colour_time_kernel(
        np.ascontiguousarray(depth_m, np.float32), np.ascontiguousarray(colour_from_depth[:3, :3], np.float64),
        np.ascontiguousarray(colour_from_depth[:3, 3], np.float64), float(K[0, 0]), float(K[1, 1]), float(K[0, 2]),
        float(K[1, 2]))


def depth_at_colour_time_reference(depth_m: np.ndarray, K: np.ndarray, colour_from_depth: np.ndarray) -> np.ndarray:
    """Slow twin of :func:`depth_at_colour_time`, on whole arrays."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    height, width = depth_m.shape
    rows, columns = np.mgrid[0:height, 0:width].astype(np.float64)
    z = depth_m.astype(np.float64)
    rotation, translation = colour_from_depth[:3, :3], colour_from_depth[:3, 3]

    def moved(column, row, depth):
        x, y = pinhole_ray(column, row, fx, fy, cx, cy)
        return np.stack([x * depth, y * depth, depth], axis=-1) @ rotation.T + translation

    points = moved(columns, rows, z)
    valid = (z > 0) & (points[..., 2] > MIN_DEPTH_M)
    u, v = pinhole(points[..., 0], points[..., 1], np.where(valid, points[..., 2], 1.0), fx, fy, cx, cy)
    source_column = np.floor(2.0 * columns - u + 0.5)
    source_row = np.floor(2.0 * rows - v + 0.5)
    valid &= (source_column >= 0) & (source_row >= 0) & (source_column < width) & (source_row < height)
    source_column = np.where(valid, source_column, 0).astype(np.int64)
    source_row = np.where(valid, source_row, 0).astype(np.int64)
    source_z = z[source_row, source_column]
    valid &= source_z > 0
    out = moved(source_column.astype(np.float64), source_row.astype(np.float64), source_z)[..., 2]
    return np.where(valid, out, 0.0).astype(np.float32)
