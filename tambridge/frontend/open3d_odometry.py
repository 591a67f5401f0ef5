"""Plain frame-to-frame Open3D RGB-D odometry (hybrid photometric + geometric term): the peer frontend.

Each frame is registered to the previous one and the relative motions are chained, so drift grows without
bound; this is what users get from Open3D's odometry alone and what our frontends are measured against.
"""

from __future__ import annotations

import logging

import numpy as np
import open3d as o3d

from tambridge.camera import Camera
from tambridge.geometry import inverse
from tambridge.io.tum import Frame

logger = logging.getLogger("tambridge.frontend.open3d_odometry")


def to_open3d_rgbd(frame: Frame, max_depth_m: float) -> o3d.geometry.RGBDImage:
    """Open3D RGBD image of a frame: intensity from colour, depth in metres truncated at ``max_depth_m``."""
    return o3d.geometry.RGBDImage.create_from_color_and_depth(
        o3d.geometry.Image(np.ascontiguousarray(frame.rgb)),
        o3d.geometry.Image(np.ascontiguousarray(frame.depth_m)),
        depth_scale=1.0,
        depth_trunc=max_depth_m,
        convert_rgb_to_intensity=True,
    )


def to_open3d_intrinsic(camera: Camera) -> o3d.camera.PinholeCameraIntrinsic:
    return o3d.camera.PinholeCameraIntrinsic(camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy)


def odometry_step(
    source: o3d.geometry.RGBDImage,
    target: o3d.geometry.RGBDImage,
    camera: Camera,
    target_from_source_init: np.ndarray | None = None,
    max_depth_m: float = 4.0,
    depth_diff_max_m: float = 0.07,
) -> tuple[bool, np.ndarray, np.ndarray]:
    """Register two RGB-D images: ``(success, target_from_source 4x4, information 6x6)``.

    Open3D's transform maps source-camera points into the target camera: ``p_target = T @ p_source``.
    """
    option = o3d.pipelines.odometry.OdometryOption(depth_diff_max=depth_diff_max_m, depth_min=0.1, depth_max=max_depth_m)
    success, target_from_source, information = o3d.pipelines.odometry.compute_rgbd_odometry(
        source,
        target,
        to_open3d_intrinsic(camera),
        np.eye(4) if target_from_source_init is None else target_from_source_init,
        o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm(),
        option,
    )
    return bool(success), np.asarray(target_from_source), np.asarray(information)


class FrameToFrameOdometry:
    """Chains frame-to-frame odometry into ``world_from_camera`` poses; the first frame is the world frame.

    A failed registration keeps the constant-velocity prediction and is counted in ``lost_frames``, with a warning.
    """

    def __init__(self, camera: Camera, max_depth_m: float = 4.0, depth_diff_max_m: float = 0.07) -> None:
        self.camera = camera
        self.max_depth_m = max_depth_m
        self.depth_diff_max_m = depth_diff_max_m
        self.lost_frames = 0
        self._previous: o3d.geometry.RGBDImage | None = None
        self._world_from_previous = np.eye(4)
        self._previous_from_current_motion = np.eye(4)

    def track(self, frame: Frame) -> np.ndarray:
        """``world_from_camera`` (4, 4) of this frame."""
        current = to_open3d_rgbd(frame, self.max_depth_m)
        if self._previous is None:
            self._previous = current
            return self._world_from_previous.copy()
        success, current_from_previous, _ = odometry_step(
            self._previous,
            current,
            self.camera,
            inverse(self._previous_from_current_motion),
            self.max_depth_m,
            self.depth_diff_max_m,
        )
        if success:
            self._previous_from_current_motion = inverse(current_from_previous)
        else:
            self.lost_frames += 1
            logger.warning("frame %d (t=%.6f): RGB-D odometry failed; keeping the constant-velocity prediction",
                           frame.index, frame.timestamp_s)
        self._world_from_previous = self._world_from_previous @ self._previous_from_current_motion
        self._previous = current
        return self._world_from_previous.copy()
