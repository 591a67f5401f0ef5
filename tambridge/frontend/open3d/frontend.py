"""The Open3D frontend (``frontend: open3d``): RGB-D odometry to the last keyframe and a keyframe pose graph.

As Open3D's reconstruction system builds a fragment: each frame is registered to the current keyframe with
hybrid (photometric + geometric) RGB-D odometry, seeded by the constant-velocity prediction; a frame becomes
a keyframe when it has moved or turned enough from the last one (or after ``keyframe_max_frames``). Every
keyframe is a pose-graph node with an odometry edge (Open3D's information matrix) to the previous one. Loop
candidates are earlier keyframes whose camera centre and viewing direction are near; each is verified by
point-to-plane ICP between voxel-downsampled clouds and, if it holds, added as an uncertain edge that Open3D's
``global_optimization`` (with its line process) may still prune. The graph is optimised whenever a loop edge
is added and at ``finish()``. This frontend keeps no sparse map: keyframe events carry empty point arrays.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from contextlib import contextmanager

import numpy as np
import open3d as o3d

from tambridge.camera import Camera
from tambridge.state import attribute_state, restore_attributes
from tambridge.frontend.open3d.odometry import odometry_step, to_open3d_intrinsic, to_open3d_rgbd
from tambridge.frontend.pose_graph import PoseEdge, optimise_pose_graph
from tambridge.frontend.contract import FrontendResult, KeyframeEvent, TrackResult, empty_timings
from tambridge.frontend.open3d.config import Open3dFrontendConfig
from tambridge.geometry import exp_se3, inverse, log_se3
from tambridge.io.tum import Frame
from tambridge.trajectory import Trajectory

logger = logging.getLogger("tambridge.frontend.open3d")


@dataclasses.dataclass
class _Keyframe:
    id: int
    frame_index: int
    timestamp_s: float
    world_from_camera: np.ndarray
    cloud: o3d.geometry.PointCloud  # camera frame, voxel-downsampled, with normals


def _motion_size(a_from_b: np.ndarray) -> tuple[float, float]:
    """(translation metres, rotation degrees) of a relative pose."""
    twist = log_se3(a_from_b)
    return float(np.linalg.norm(a_from_b[:3, 3])), float(np.degrees(np.linalg.norm(twist[3:])))


class Open3dFrontend:
    """Keyframe RGB-D odometry with a loop-closing pose graph; same interface as the ORB frontend."""

    def __init__(
        self,
        camera: Camera,
        config: Open3dFrontendConfig | None = None,
        world_from_first_camera: np.ndarray | None = None,
    ) -> None:
        self.camera = camera
        # A fresh default each time: the config dataclasses are mutable (``--set`` writes into them).
        self.config = config if config is not None else Open3dFrontendConfig()
        self.timings_s = empty_timings()
        self.frames_lost = 0
        self.loops_closed = 0
        self._intrinsic = to_open3d_intrinsic(camera)
        self._world_from_first = np.eye(4) if world_from_first_camera is None else np.asarray(world_from_first_camera, float)
        self._keyframes: list[_Keyframe] = []
        self._edges: list[PoseEdge] = []
        self._keyframe_rgbd: o3d.geometry.RGBDImage | None = None
        self._keyframe_from_last = np.eye(4)
        self._last_from_current = np.eye(4)  # constant-velocity prior
        self._frames_since_keyframe = 0
        self._keyframe_requested = False
        self._records: list[tuple[int, float, int, np.ndarray, bool]] = []

    @contextmanager
    def _timed(self, stage: str):
        start = time.perf_counter()
        try:
            yield
        finally:
            self.timings_s[stage] += time.perf_counter() - start

    extract = None
    """Nothing of tracking a frame runs ahead (:attr:`~tambridge.frontend.contract.Frontend.extract`)."""

    def track(self, frame: Frame, features: None = None) -> TrackResult:
        """Register one frame to the current keyframe (frames in order); see :class:`TrackResult`. ``features`` is
        None: this frontend has no ``extract``."""
        config = self.config
        with self._timed("features"):
            rgbd = to_open3d_rgbd(frame, config.max_depth_m)
        if not self._keyframes:
            event = self._add_keyframe(frame, rgbd, self._world_from_first, None)
            self._record(frame, np.eye(4), True)
            return TrackResult(frame.index, frame.timestamp_s, self._world_from_first.copy(), True, True, 0, keyframe=event)
        keyframe = self._keyframes[-1]
        guess = self._keyframe_from_last @ self._last_from_current
        with self._timed("matching"):
            success, keyframe_from_current, information = odometry_step(
                rgbd, self._keyframe_rgbd, self.camera, guess, config.max_depth_m, config.depth_diff_max_m
            )
        # Project onto SE(3): Open3D's float round-off would otherwise grow through the motion prior.
        keyframe_from_current = exp_se3(log_se3(keyframe_from_current))
        if not success:
            self.frames_lost += 1
            keyframe_from_current = guess
            logger.warning("frame %d (t=%.6f): RGB-D odometry to keyframe %d failed; its pose is the "
                           "constant-velocity prediction", frame.index, frame.timestamp_s, keyframe.id)
        self._last_from_current = inverse(self._keyframe_from_last) @ keyframe_from_current
        self._keyframe_from_last = keyframe_from_current
        self._frames_since_keyframe += 1
        world_from_camera = keyframe.world_from_camera @ keyframe_from_current
        translation_m, rotation_deg = _motion_size(keyframe_from_current)
        event, loop_closed = None, False
        if success and (translation_m > config.keyframe_translation_m or rotation_deg > config.keyframe_rotation_deg
                        or self._frames_since_keyframe >= config.keyframe_max_frames or self._keyframe_requested):
            event, loop_closed = self._new_keyframe(frame, rgbd, world_from_camera, keyframe_from_current, information)
            world_from_camera = self._keyframes[-1].world_from_camera
            self._record(frame, np.eye(4), True)
        else:
            self._record(frame, keyframe_from_current, success)
        return TrackResult(frame.index, frame.timestamp_s, world_from_camera.copy(), success, event is not None,
                           inlier_count=0, loop_closed=loop_closed, keyframe=event)

    def _add_keyframe(self, frame: Frame, rgbd, world_from_camera: np.ndarray, odometry) -> KeyframeEvent:
        config = self.config
        with self._timed("features"):
            cloud = o3d.geometry.PointCloud.create_from_rgbd_image(rgbd, self._intrinsic)
            cloud = cloud.voxel_down_sample(config.loop_voxel_m)
            cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.5 * config.loop_voxel_m, max_nn=30))
        keyframe = _Keyframe(len(self._keyframes), frame.index, frame.timestamp_s, world_from_camera.copy(), cloud)
        if odometry is not None:
            previous_from_new, information = odometry
            self._edges.append(PoseEdge(keyframe.id, keyframe.id - 1, previous_from_new, information, uncertain=False))
        self._keyframes.append(keyframe)
        self._keyframe_rgbd = rgbd
        self._keyframe_from_last = np.eye(4)
        self._frames_since_keyframe = 0
        self._keyframe_requested = False
        return KeyframeEvent(
            keyframe_id=keyframe.id, frame_index=frame.index, timestamp_s=frame.timestamp_s,
            world_from_camera=world_from_camera.copy(), points_world_m=np.zeros((0, 3)), keypoints_px=np.zeros((0, 2)),
            map_point_ids=np.zeros(0, np.int64), shared_with_previous=0, previous_total=0,
        )

    def _new_keyframe(self, frame, rgbd, world_from_camera, previous_from_new, information) -> tuple[KeyframeEvent, bool]:
        self._add_keyframe(frame, rgbd, world_from_camera, (previous_from_new, information))
        loop_closed = False
        with self._timed("loop"):
            if self._add_loop_edges(self._keyframes[-1]):
                self._optimise()
                loop_closed = True
        keyframe = self._keyframes[-1]
        event = KeyframeEvent(
            keyframe_id=keyframe.id, frame_index=frame.index, timestamp_s=frame.timestamp_s,
            world_from_camera=keyframe.world_from_camera.copy(), points_world_m=np.zeros((0, 3)),
            keypoints_px=np.zeros((0, 2)), map_point_ids=np.zeros(0, np.int64), shared_with_previous=0, previous_total=0,
        )
        return event, loop_closed

    def _add_loop_edges(self, keyframe: _Keyframe) -> bool:
        """Verified loop edges from the new keyframe to near earlier keyframes; True if any was added."""
        config = self.config
        earlier = self._keyframes[: max(0, keyframe.id - config.loop_min_keyframe_gap + 1)]
        if not earlier:
            return False
        centres = np.stack([k.world_from_camera[:3, 3] for k in earlier])
        axes = np.stack([k.world_from_camera[:3, 2] for k in earlier])
        distance = np.linalg.norm(centres - keyframe.world_from_camera[:3, 3], axis=1)
        angle = np.degrees(np.arccos(np.clip(axes @ keyframe.world_from_camera[:3, 2], -1.0, 1.0)))
        near = np.flatnonzero((distance < config.loop_radius_m) & (angle < config.loop_max_angle_deg))
        added = False
        for index in near[np.argsort(distance[near])][: config.loop_max_candidates]:
            candidate = earlier[index]
            guess = inverse(candidate.world_from_camera) @ keyframe.world_from_camera  # candidate_from_new
            result = o3d.pipelines.registration.registration_icp(
                keyframe.cloud, candidate.cloud, config.loop_icp_distance_m, guess,
                o3d.pipelines.registration.TransformationEstimationPointToPlane(),
            )
            if result.fitness < config.loop_min_fitness or result.inlier_rmse > config.loop_max_rmse_m:
                continue
            information = o3d.pipelines.registration.get_information_matrix_from_point_clouds(
                keyframe.cloud, candidate.cloud, config.loop_icp_distance_m, result.transformation
            )
            self._edges.append(PoseEdge(keyframe.id, candidate.id, np.asarray(result.transformation), information, uncertain=True))
            logger.info("loop edge: keyframe %d (frame %d) to keyframe %d (frame %d), ICP fitness %.2f, rmse %.3f m",
                        keyframe.id, keyframe.frame_index, candidate.id, candidate.frame_index,
                        result.fitness, result.inlier_rmse)
            added = True
        return added

    def _optimise(self) -> None:
        """Global optimisation of the keyframe graph (keyframe 0 fixed)."""
        config = self.config
        optimised, kept = optimise_pose_graph(
            np.stack([k.world_from_camera for k in self._keyframes]), self._edges, reference_node=0,
            edge_prune_threshold=config.edge_prune_threshold, preference_loop_closure=config.preference_loop_closure,
            max_correspondence_distance_m=config.loop_icp_distance_m,
        )
        for keyframe, pose in zip(self._keyframes, optimised):
            keyframe.world_from_camera = pose
        self.loops_closed = kept

    def _record(self, frame: Frame, keyframe_from_camera: np.ndarray, tracked: bool) -> None:
        self._records.append((frame.index, frame.timestamp_s, self._keyframes[-1].id, keyframe_from_camera.copy(), tracked))

    def request_keyframe(self) -> None:
        """Make the next successfully registered frame a keyframe."""
        self._keyframe_requested = True

    def keyframe_poses(self) -> dict[int, np.ndarray]:
        """Keyframe id -> ``world_from_camera`` (4, 4) after the latest optimisation."""
        return {k.id: k.world_from_camera.copy() for k in self._keyframes}

    def finish(self) -> FrontendResult:
        """Final pose-graph optimisation and trajectories; call once, after the last frame."""
        if any(e.uncertain for e in self._edges):
            with self._timed("global_ba"):
                self._optimise()
        poses = [self._keyframes[k].world_from_camera @ relative for _, _, k, relative, _ in self._records]
        tracked = np.array([r[4] for r in self._records], bool)
        keyframes = self._keyframes
        return FrontendResult(
            # A frame whose odometry failed has the prediction from the frames before it; those after it place it better.
            trajectory=Trajectory(np.array([r[1] for r in self._records]), np.stack(poses)).bridged(tracked),
            tracked=tracked,
            keyframe_trajectory=Trajectory(np.array([k.timestamp_s for k in keyframes]), np.stack([k.world_from_camera for k in keyframes])),
            keyframe_poses=self.keyframe_poses(),
            keyframe_frame_indices={k.id: k.frame_index for k in keyframes},
            map_points_world_m=np.zeros((0, 3)),
            map_point_colours=np.zeros((0, 3), np.uint8),
            map_point_ids=np.zeros(0, np.int64),
            timings_s=dict(self.timings_s),
            frames_lost=self.frames_lost,
            frames_relocalised=0,
            loops_closed=self.loops_closed,
        )

    def state_dict(self) -> dict:
        """Everything a resumed run needs (keyframes, pose graph, motion model, frame records), for checkpoints."""
        return attribute_state(self, ("camera", "config", "_intrinsic"))

    def load_state_dict(self, state: dict) -> None:
        """Continue from :meth:`state_dict` (on a frontend built with the same camera and config)."""
        restore_attributes(self, state)
