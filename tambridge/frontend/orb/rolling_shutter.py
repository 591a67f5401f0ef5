"""Keypoints moved to their frame's time, for colour cameras with a rolling shutter.

A rolling shutter exposes the image's rows one after another: row ``v`` of an image of height ``H`` is taken
``(v / H - 1/2) * readout_s`` after the frame's stamp (the middle row at the stamp,
:func:`~tambridge.camera.rolling_shutter_row_times_s`). A moving camera then sees each
row from a slightly different pose, which a tracker solving for one pose per frame takes as a distortion of the
scene. Under the constant-velocity prior, a camera twist ``xi`` per second (``camera(t + s)_from_camera(t) =
exp(s xi)``), a point seen at row time ``dt`` at camera point ``X`` lies at ``exp(-dt xi) X`` in the camera at the
stamp; :func:`keypoints_at_frame_time` moves each keypoint there (to first order in ``dt``, exact to well under
0.1 px for a camera turning at 1 rad/s and a readout of 30 ms).
:func:`keypoints_at_frame_time_reference` is its exact twin.
"""

from __future__ import annotations

import numpy as np

from tambridge.camera import Camera, rolling_shutter_row_times_s
from tambridge.geometry import exp_se3, log_se3


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
    depth = _depth_or_median(depth_m)
    points = camera.backproject(keypoints_px, depth)
    dt = rolling_shutter_row_times_s(keypoints_px[:, 1], camera.height, readout_s)
    rho, phi = twist_per_s[:3], twist_per_s[3:]
    velocity = np.cross(phi, points) + (rho if np.any(depth_m > 0) else 0.0)
    moved = points - dt[:, None] * velocity
    return camera.project(moved)


def keypoints_at_frame_time_reference(keypoints_px: np.ndarray, depth_m: np.ndarray, camera: Camera,
                                      twist_per_s: np.ndarray, readout_s: float) -> np.ndarray:
    """Slow twin of :func:`keypoints_at_frame_time`: one exact ``exp_se3`` per keypoint."""
    depth = _depth_or_median(depth_m)
    twist = np.asarray(twist_per_s, np.float64).copy()
    if not np.any(depth_m > 0):
        twist[:3] = 0.0
    out = np.zeros_like(keypoints_px, dtype=np.float64)
    for index, (pixel, z) in enumerate(zip(keypoints_px, depth)):
        dt = rolling_shutter_row_times_s(np.array([pixel[1]]), camera.height, readout_s)[0]
        point = exp_se3(-dt * twist) @ np.append(camera.backproject(pixel, z), 1.0)
        out[index] = camera.project(point[:3])
    return out


def _depth_or_median(depth_m: np.ndarray) -> np.ndarray:
    """Depth (N,) with the keypoints without depth at the median of those with it (1 m where none has it: then
    only rotation moves the keypoints, which is independent of depth)."""
    valid = depth_m > 0
    fill = float(np.median(depth_m[valid])) if valid.any() else 1.0
    return np.where(valid, depth_m, fill)
