"""Keypoints and images moved to their frame's time, for colour cameras with a rolling shutter.

A rolling shutter exposes the image's rows one after another: row ``v`` of an image of height ``H`` is taken
``(v / H - 1/2) * readout_s`` after the frame's stamp (the middle row at the stamp,
:func:`~tambridge.camera.rolling_shutter_row_times_s`). A moving camera then sees each row from a slightly different
pose, which a tracker or a map solving for one pose per frame takes as a distortion of the scene. Under a constant
velocity, a camera twist ``xi`` per second (``camera(t + s)_from_camera(t) = exp(s xi)``, :func:`camera_twist_per_s`),
a point seen at row time ``dt`` at camera point ``X`` lies at ``exp(-dt xi) X`` in the camera at the stamp.

- :func:`keypoints_at_frame_time` moves keypoints (with their depths) there, for tracking;
- :func:`image_at_frame_time` resamples a whole colour image (with the frame's depth) to what a global shutter at
  the stamp would have taken, for mapping.

Both are first order in ``dt`` (exact to well under 0.1 px for a camera turning at 1 rad/s and a readout of 30 ms);
their ``_reference`` twins are exact.
"""

from __future__ import annotations

import numba
import numpy as np

from tambridge.camera import Camera, pinhole_inverse_depth_numba, rolling_shutter_row_times_s
from tambridge.geometry import exp_se3, log_se3

ROW_TIME_ITERATIONS = 3
"""Fixed-point steps that find the row a point of the stamp's image was read at (the row depends on the time)."""


def camera_twist_per_s(current_from_previous: np.ndarray, frame_interval_s: float) -> np.ndarray:
    """The twist ``(rho, phi)`` (6,) per second of a camera that moves by ``current_from_previous`` (4, 4) over
    ``frame_interval_s`` at constant velocity."""
    return log_se3(current_from_previous) / frame_interval_s


def keypoints_at_frame_time(keypoints_px: np.ndarray, depth_m: np.ndarray, camera: Camera, twist_per_s: np.ndarray,
                            readout_s: float) -> np.ndarray:
    """Keypoints (N, 2) px where the camera at the frame's stamp sees the points it saw at their rows' times.

    ``depth_m`` (N,): each keypoint's depth; where it has none (0) the median of the others stands in (the whole
    image's median motion), or only the rotation moves it when no keypoint has depth.
    """
    if len(keypoints_px) == 0:
        return keypoints_px
    depth, twist = _depth_and_twist(depth_m, twist_per_s)
    points = camera.backproject(keypoints_px, depth)
    dt = rolling_shutter_row_times_s(keypoints_px[:, 1], camera.height, readout_s)
    moved = points - dt[:, None] * (np.cross(twist[3:], points) + twist[:3])
    return camera.project(moved)


def keypoints_at_frame_time_reference(keypoints_px: np.ndarray, depth_m: np.ndarray, camera: Camera,
                                      twist_per_s: np.ndarray, readout_s: float) -> np.ndarray:
    """Slow twin of :func:`keypoints_at_frame_time`: one exact ``exp_se3`` per keypoint."""
    depth, twist = _depth_and_twist(depth_m, twist_per_s)
    out = np.zeros_like(keypoints_px, dtype=np.float64)
    for index, (pixel, z) in enumerate(zip(keypoints_px, depth)):
        dt = rolling_shutter_row_times_s(np.array([pixel[1]]), camera.height, readout_s)[0]
        point = exp_se3(-dt * twist) @ np.append(camera.backproject(pixel, z), 1.0)
        out[index] = camera.project(point[:3])
    return out


def image_at_frame_time(rgb: np.ndarray, depth_m: np.ndarray, camera: Camera, twist_per_s: np.ndarray,
                        readout_s: float) -> np.ndarray:
    """The colour image (H, W, 3) uint8 a global shutter at the frame's stamp would take, from the rolling-shutter
    image ``rgb`` (H, W, 3) uint8 and the frame's depth ``depth_m`` (H, W) metres (0: none; the median depth stands
    in there): each pixel looks up, bilinearly, where the rolling shutter saw its point (the row found by
    :data:`ROW_TIME_ITERATIONS` fixed-point steps; outside the image, the nearest border pixel). A numba kernel;
    :func:`image_at_frame_time_reference` is its twin."""
    depth, twist = _depth_and_twist(depth_m, twist_per_s)
    return _image_at_frame_time_kernel(np.ascontiguousarray(rgb), np.ascontiguousarray(depth, np.float64),
                                       np.ascontiguousarray(twist, np.float64), float(readout_s), float(camera.fx),
                                       float(camera.fy), float(camera.cx), float(camera.cy))


@numba.njit(cache=True, nogil=True)
def _image_at_frame_time_kernel(rgb, depth_m, twist, readout_s, fx, fy, cx, cy):
    height, width = depth_m.shape
    out = np.empty_like(rgb)
    rho, phi = twist[:3], twist[3:]
    # Divisions dominate this loop: reciprocals taken once, and one division per fixed-point step (1 / z).
    inverse_fx, inverse_fy, inverse_height = 1.0 / fx, 1.0 / fy, 1.0 / height
    for row in range(height):
        y = (row - cy) * inverse_fy
        for column in range(width):
            z = depth_m[row, column]
            px, py, pz = (column - cx) * inverse_fx * z, y * z, z
            # The point's motion per second in the camera: phi x p + rho.
            vx = phi[1] * pz - phi[2] * py + rho[0]
            vy = phi[2] * px - phi[0] * pz + rho[1]
            vz = phi[0] * py - phi[1] * px + rho[2]
            u, v = float(column), float(row)
            for _ in range(ROW_TIME_ITERATIONS):
                dt = (v * inverse_height - 0.5) * readout_s  # rolling_shutter_row_times_s
                u, v = pinhole_inverse_depth_numba(px + dt * vx, py + dt * vy, 1.0 / (pz + dt * vz), fx, fy, cx, cy)
            u = min(max(u, 0.0), width - 1.0)
            v = min(max(v, 0.0), height - 1.0)
            left, top = min(int(u), width - 2), min(int(v), height - 2)
            a, b = u - left, v - top
            for channel in range(rgb.shape[2]):
                value = ((1 - a) * (1 - b) * rgb[top, left, channel] + a * (1 - b) * rgb[top, left + 1, channel]
                         + (1 - a) * b * rgb[top + 1, left, channel] + a * b * rgb[top + 1, left + 1, channel])
                out[row, column, channel] = min(255.0, value + 0.5)
    return out


def image_at_frame_time_reference(rgb: np.ndarray, depth_m: np.ndarray, camera: Camera, twist_per_s: np.ndarray,
                                  readout_s: float) -> np.ndarray:
    """Slow twin of :func:`image_at_frame_time`: each pixel's point moved by the exact rigid motion over its row time
    (the exponential map, per pixel), on whole arrays, and sampled with cv2.remap."""
    import cv2
    from scipy.spatial.transform import Rotation

    depth, twist = _depth_and_twist(depth_m, twist_per_s)
    height, width = depth.shape
    rows, columns = np.mgrid[0:height, 0:width].astype(np.float64)
    points = camera.backproject(np.stack([columns, rows], axis=-1), depth).reshape(-1, 3)
    v = rows.reshape(-1)
    for _ in range(ROW_TIME_ITERATIONS):
        dt = rolling_shutter_row_times_s(v, height, readout_s)
        # exp(dt xi) = [R, V rho]: R from the rotation vector dt phi, V = I + b [phi]x + c [phi]x^2 (exp_se3's).
        phi, rho = dt[:, None] * twist[3:], dt[:, None] * twist[:3]
        angle = np.maximum(np.linalg.norm(phi, axis=1), 1e-12)[:, None]
        b, c = (1.0 - np.cos(angle)) / angle**2, (angle - np.sin(angle)) / angle**3
        translation = rho + b * np.cross(phi, rho) + c * np.cross(phi, np.cross(phi, rho))
        moved = Rotation.from_rotvec(phi).apply(points) + translation
        uv = camera.project(moved)
        u, v = uv[:, 0], uv[:, 1]
    map_x = np.clip(u, 0, width - 1).reshape(height, width).astype(np.float32)
    map_y = np.clip(v, 0, height - 1).reshape(height, width).astype(np.float32)
    return cv2.remap(rgb, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _depth_and_twist(depth_m: np.ndarray, twist_per_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depth with the pixels or keypoints without depth (0) at the median of those with it, and the twist; where
    nothing has depth, depth 1 m and the twist's translation dropped (then only the rotation moves points, which
    is independent of depth)."""
    valid = depth_m > 0
    twist = np.asarray(twist_per_s, np.float64).copy()
    if not valid.any():
        twist[:3] = 0.0
        return np.ones_like(depth_m, dtype=np.float64), twist
    return np.where(valid, depth_m, float(np.median(depth_m[valid]))).astype(np.float64), twist
