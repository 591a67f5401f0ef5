"""Plain frame-to-frame Open3D RGB-D odometry (hybrid photometric + geometric term): the peer frontend.

Each frame is registered to the previous one and the relative motions are chained, so drift grows without
bound; this is what users get from Open3D's odometry alone and what our frontends are measured against.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import open3d as o3d

from tambridge.camera import Camera
from tambridge.state import attribute_state, restore_attributes
from tambridge.geometry import inverse, rotation_angle_deg
from tambridge.frontend.contract import FrontendResult, KeyframeEvent, TrackResult, empty_timings
from tambridge.io.tum import Frame
from tambridge.trajectory import Trajectory

logger = logging.getLogger("tambridge.frontend.open3d.odometry")


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

    Follows the :class:`~tambridge.frontend.contract.Frontend` protocol so it can stand in for the other
    frontends. It has no map, so its keyframes (chosen by motion since the last one, for the mapper's sake)
    carry empty matched-point arrays and nothing is ever corrected. A failed registration keeps the
    constant-velocity prediction, is counted as lost and logged as a warning.
    """

    def __init__(
        self,
        camera: Camera,
        max_depth_m: float = 4.0,
        depth_diff_max_m: float = 0.07,
        keyframe_translation_m: float = 0.10,
        keyframe_rotation_deg: float = 10.0,
    ) -> None:
        self.camera = camera
        self.max_depth_m = max_depth_m
        self.depth_diff_max_m = depth_diff_max_m
        self.keyframe_translation_m = keyframe_translation_m
        self.keyframe_rotation_deg = keyframe_rotation_deg
        self._previous: o3d.geometry.RGBDImage | None = None
        self._world_from_previous = np.eye(4)
        self._previous_from_current_motion = np.eye(4)
        self._poses: list[np.ndarray] = []
        self._timestamps: list[float] = []
        self._tracked: list[bool] = []
        self._keyframe_poses: dict[int, np.ndarray] = {}
        self._keyframe_frame_indices: dict[int, int] = {}
        self._keyframe_timestamps: dict[int, float] = {}
        self._keyframe_requested = False
        self._seconds = 0.0

    extract = None
    """Nothing of tracking a frame runs ahead (:attr:`~tambridge.frontend.contract.Frontend.extract`)."""

    def track(self, frame: Frame, features: None = None) -> TrackResult:
        """Register one frame to the previous one (frames in order). ``features`` is None: this frontend has no
        ``extract``."""
        started = time.perf_counter()
        current = to_open3d_rgbd(frame, self.max_depth_m)
        success = True
        if self._previous is not None:
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
                logger.warning("frame %d (t=%.6f): RGB-D odometry failed; keeping the constant-velocity prediction",
                               frame.index, frame.timestamp_s)
            self._world_from_previous = self._world_from_previous @ self._previous_from_current_motion
        self._previous = current
        world_from_camera = self._world_from_previous.copy()
        self._poses.append(world_from_camera)
        self._timestamps.append(frame.timestamp_s)
        self._tracked.append(success)
        keyframe = None
        if self._is_new_keyframe(world_from_camera) or (success and self._keyframe_requested):
            self._keyframe_requested = False
            keyframe_id = len(self._keyframe_poses)
            self._keyframe_poses[keyframe_id] = world_from_camera
            self._keyframe_frame_indices[keyframe_id] = frame.index
            self._keyframe_timestamps[keyframe_id] = frame.timestamp_s
            keyframe = KeyframeEvent(
                keyframe_id, frame.index, frame.timestamp_s, world_from_camera,
                np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0, np.int64), 0, 0,
            )
        self._seconds += time.perf_counter() - started
        return TrackResult(frame.index, frame.timestamp_s, world_from_camera, success, keyframe is not None,
                           inlier_count=0, keyframe=keyframe)

    def _is_new_keyframe(self, world_from_camera: np.ndarray) -> bool:
        if not self._keyframe_poses:
            return True
        last_from_current = inverse(self._keyframe_poses[len(self._keyframe_poses) - 1]) @ world_from_camera
        return bool(np.linalg.norm(last_from_current[:3, 3]) > self.keyframe_translation_m
                    or rotation_angle_deg(last_from_current) > self.keyframe_rotation_deg)

    def request_keyframe(self) -> None:
        """Make the next successfully registered frame a keyframe."""
        self._keyframe_requested = True

    def keyframe_poses(self) -> dict[int, np.ndarray]:
        return dict(self._keyframe_poses)

    def finish(self) -> FrontendResult:
        keyframe_ids = sorted(self._keyframe_poses)
        timings = empty_timings()
        timings["odometry"] = self._seconds
        return FrontendResult(
            trajectory=Trajectory(np.array(self._timestamps), np.stack(self._poses)),
            tracked=np.array(self._tracked),
            keyframe_trajectory=Trajectory(
                np.array([self._keyframe_timestamps[k] for k in keyframe_ids]),
                np.stack([self._keyframe_poses[k] for k in keyframe_ids]),
            ),
            keyframe_poses=self.keyframe_poses(),
            keyframe_frame_indices=dict(self._keyframe_frame_indices),
            map_points_world_m=np.zeros((0, 3)),
            map_point_colours=np.zeros((0, 3), np.uint8),
            map_point_ids=np.zeros(0, np.int64),
            timings_s=timings,
            frames_lost=int(np.sum(~np.array(self._tracked))),
            frames_relocalised=0,
            loops_closed=0,
        )

    def state_dict(self) -> dict:
        """Everything a resumed run needs (previous frame, motion model, poses, keyframes), for checkpoints."""
        return attribute_state(self, ("camera",))

    def load_state_dict(self, state: dict) -> None:
        """Continue from :meth:`state_dict` (on a frontend built with the same camera and config)."""
        restore_attributes(self, state)
