"""What the frontends hand to the rest of the pipeline.

The frontends (:class:`~tambridge.frontend.orb.frontend.OrbFrontend`,
:class:`~tambridge.frontend.open3d.frontend.Open3dFrontend` and
:class:`~tambridge.frontend.open3d.odometry.FrameToFrameOdometry`) follow :class:`Frontend`: ``track(frame)``
once per frame in order (with the frame's ``extract(frame)`` made ahead, where the frontend has one),
``keyframe_poses()`` at any time (poses after the latest loop correction), ``finish()`` once at the end. All
poses are 4x4 float64 ``world_from_camera``; the first frame's camera is the world frame unless the frontend
is given another ``world_from_first_camera``.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Protocol

import numpy as np

from tambridge.io.tum import Frame
from tambridge.trajectory import Trajectory

STAGES = ("features", "matching", "pnp", "local_ba", "loop", "global_ba")


@dataclasses.dataclass
class KeyframeEvent:
    """A new keyframe, as the Fusion Bridge needs it.

    ``points_world_m`` (M, 3) are the map points matched in this keyframe at ``keypoints_px`` (M, 2), with
    ``map_point_ids`` (M,) int64, leaving out the points lifted from this keyframe's own keypoints (they
    reproject exactly at its pose and say nothing about it). ``shared_with_previous`` is M(i-1, i), the map points this keyframe shares
    with the previous keyframe; ``previous_total`` is T(i-1, i), the matched map points of the previous
    keyframe (paper eq. 3: selected if beta <= M < alpha * T). ``world_from_camera`` and the points are as at
    insertion (before local BA when the ORB frontend maps in its background thread); local BA and loop closure
    move them later, so ask ``keyframe_poses()`` for a keyframe's current pose. For the Open3D frontend the
    three arrays are empty, ``shared_with_previous`` is 0 and ``previous_total`` is 0 (it has no sparse map).
    """

    keyframe_id: int
    frame_index: int
    timestamp_s: float
    world_from_camera: np.ndarray
    points_world_m: np.ndarray
    keypoints_px: np.ndarray
    map_point_ids: np.ndarray
    shared_with_previous: int
    previous_total: int


@dataclasses.dataclass
class TrackResult:
    """Outcome of one ``track(frame)`` call.

    ``tracked`` is False when the frame could not be localised; its pose is then the constant-velocity
    prediction (and a warning was logged). ``loop_closed`` says keyframe poses moved: ask ``keyframe_poses()``.
    """

    frame_index: int
    timestamp_s: float
    world_from_camera: np.ndarray
    tracked: bool
    is_keyframe: bool
    inlier_count: int
    relocalised: bool = False
    loop_closed: bool = False
    keyframe: KeyframeEvent | None = None


@dataclasses.dataclass
class MapPointObservations:
    """Where the keyframes see the good map points of a :class:`FrontendResult`, one row per observation.

    Observation ``o`` is of point ``point_rows[o]`` (a row of the result's ``map_points_world_m``) in keyframe
    ``keyframe_ids[o]``, at ``keypoints_px[o]`` (pixels of the frames' camera, distortion removed). ``point_rows``
    and ``keyframe_ids`` (O,) int64, ``keypoints_px`` (O, 2) float64; a keyframe sees a point at most once.
    """

    point_rows: np.ndarray
    keyframe_ids: np.ndarray
    keypoints_px: np.ndarray

    @staticmethod
    def empty() -> "MapPointObservations":
        return MapPointObservations(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)))

    def __len__(self) -> int:
        return len(self.point_rows)


@dataclasses.dataclass
class FrontendResult:
    """Final poses after loop closure and global BA.

    ``trajectory`` has every frame given to ``track`` (non-keyframes re-anchored to their reference keyframe
    after corrections; a frame not localised between two localised ones on the geodesic between them,
    :meth:`~tambridge.trajectory.Trajectory.bridged`, where ORB also counts the first keyframe of a segment
    joined to the first keyframe's world as localised), ``tracked`` (N,) bool says which were localised;
    ``keyframe_trajectory`` the keyframes; ``keyframe_poses`` keyframe id -> 4x4; ``keyframe_frame_indices``
    keyframe id -> frame index. These three list every keyframe ever announced by a :class:`KeyframeEvent`, culled ones included (``keyframes_culled`` of
    them, ORB only): a culled keyframe's pose is its parent keyframe's final pose times the relative pose it had
    when it was culled, so Gaussians anchored to it move with the map. ``tracked_by_depth`` (N,) bool marks the
    tracked frames placed by their depth alone (ORB only, ``depth_only_tracking``; None: none were), whose colour
    the tracker could not use.
    ``map_points_world_m`` (P, 3), ``map_point_colours`` (P, 3) uint8 RGB and ``map_point_ids`` (P,) are the
    good map points (empty for Open3D), ``map_point_observations`` their observations in the keyframes (the points'
    tracks, for exporters; empty for Open3D). ``timings_s`` holds seconds per stage (keys of :data:`STAGES`).
    """

    trajectory: Trajectory
    tracked: np.ndarray
    keyframe_trajectory: Trajectory
    keyframe_poses: dict[int, np.ndarray]
    keyframe_frame_indices: dict[int, int]
    map_points_world_m: np.ndarray
    map_point_colours: np.ndarray
    map_point_ids: np.ndarray
    timings_s: dict[str, float]
    frames_lost: int
    frames_relocalised: int
    loops_closed: int
    keyframes_culled: int = 0
    tracked_by_depth: np.ndarray | None = None
    map_point_observations: MapPointObservations = dataclasses.field(default_factory=MapPointObservations.empty)

    @property
    def frames_tracked_by_depth(self) -> int:
        """How many frames ``tracked_by_depth`` marks."""
        return 0 if self.tracked_by_depth is None else int(np.count_nonzero(self.tracked_by_depth))


class Frontend(Protocol):
    """What the pipeline and the Fusion Bridge call."""

    extract: Callable[[Frame], object] | None
    """The part of tracking a frame that needs nothing from earlier frames (the ORB frontend's features), so that it
    can run a frame ahead in another thread (one frame at a time); None where a frontend has no such part (the
    Open3D ones)."""

    def track(self, frame: Frame, features: object | None = None) -> TrackResult:
        """Localise the next frame. ``features``: ``extract(frame)`` made ahead (the same result), or None to
        have ``track`` do all of it."""

    def keyframe_poses(self) -> dict[int, np.ndarray]: ...

    def request_keyframe(self) -> None:
        """Make the next tracked frame a keyframe whatever the frontend's own rule says (the mapper asks where its
        map lacks coverage)."""

    def finish(self) -> FrontendResult: ...

    def state_dict(self) -> dict: ...

    def load_state_dict(self, state: dict) -> None: ...


def empty_timings() -> dict[str, float]:
    """A timing dict with every stage at zero seconds."""
    return {stage: 0.0 for stage in STAGES}
