"""The blur model the bridge hands the mapper: the camera's motion over each mapping view's exposure.

A colour frame integrates light over its exposure ``[t - e/2, t + e/2]``; where the camera moves meanwhile, the
frame is the mean of sharp images along that motion. The bridge knows the motion from the frontend's tracked
poses of the view's frame and its neighbours (:func:`exposure_path`): when the view is mapped, the previous
tracked frame gives a constant velocity; once the next frame is tracked the path runs through both neighbours.
The mapper then renders such a view at :func:`subpose_count` poses along the path and compares their mean with
the blurred frame (:func:`tambridge.gaussians.mapper.render_exposure`); a view whose image moves less than
``bridge.blur_step_px`` over its exposure is rendered once, as before.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from tambridge.camera import Camera, exposure_offsets_s
from tambridge.geometry import inverse, poses_along

DEPTH_SAMPLE_STEP = 4
"""Every this many pixels (along rows and columns) of a view's depth measure its image motion (as the synthetic
sequence's blur does)."""


@dataclasses.dataclass
class ExposurePath:
    """The camera's motion around a view's frame: ``frame_from_tracked`` (N, 4, 4), N >= 2, poses relative to the
    frame's own (identity among them) at ``times_s`` (N,) relative to its timestamp, increasing; ``exposure_s`` the
    exposure time it is integrated over."""

    times_s: np.ndarray
    frame_from_tracked: np.ndarray
    exposure_s: float

    def offsets_s(self, count: int) -> np.ndarray:
        """(count,) sub-times, relative to the frame's timestamp: the midpoints of ``count`` equal slices of the
        exposure (0 among them for an odd count)."""
        return exposure_offsets_s(count, self.exposure_s)

    def poses(self, count: int) -> np.ndarray:
        """(count, 4, 4) ``frame_from_subpose`` at :meth:`offsets_s` along the path (:func:`poses_along`)."""
        return poses_along(self.times_s, self.frame_from_tracked, self.offsets_s(count))


def exposure_path(world_from_frame: np.ndarray, timestamp_s: float, neighbours: list[tuple[float, np.ndarray]],
                  exposure_s: float) -> ExposurePath | None:
    """The path of a frame tracked at ``world_from_frame`` (4x4) at ``timestamp_s`` through its tracked
    ``neighbours`` (timestamp, 4x4 ``world_from_camera``; the previous frame, the next, or both), or None without a
    neighbour or with ``exposure_s`` 0."""
    if exposure_s <= 0 or not neighbours:
        return None
    samples = sorted([(0.0, np.eye(4))] + [(time - timestamp_s, inverse(world_from_frame) @ pose)
                                           for time, pose in neighbours], key=lambda sample: sample[0])
    return ExposurePath(np.array([time for time, _ in samples]), np.stack([pose for _, pose in samples]), exposure_s)


def subpose_count(path: ExposurePath | None, camera: Camera, depth_m: np.ndarray, step_px: float, max_count: int) -> int:
    """Renders a view needs at ``camera``'s resolution (``depth_m`` (H, W) its depth there, 0 invalid): the image
    motion of its depth points over the exposure, start to middle to end, in steps of at most ``step_px``; odd
    (the frame's own pose the middle one), at most ``max_count`` (rounded down to odd); 1 without a path."""
    if path is None or max_count <= 1:
        return 1
    points = camera.depth_points(depth_m, DEPTH_SAMPLE_STEP)
    half = path.exposure_s / 2.0
    start, end = poses_along(path.times_s, path.frame_from_tracked, np.array([-half, half]))
    motion_px = (camera.image_motion_px(points, np.eye(4), inverse(start))
                 + camera.image_motion_px(points, np.eye(4), inverse(end)))
    count = math.ceil(motion_px / step_px)
    if count <= 1:
        return 1
    return min(count + 1 - count % 2, max_count - 1 + max_count % 2)
