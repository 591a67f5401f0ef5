"""The world of a run's exported files: gravity-aligned, z up (``export.world = upright``), or the first camera's.

A run tracks and maps in the first camera's OpenCV frame (x right, y down, z forward, tilted as the camera was):
the frontend, the mapper and checkpoints stay there. Where outputs are written, one rigid rotation about the
first camera's centre, ``upright_from_first_camera``, takes every exported pose and point into the upright world:

- z is up (against gravity);
- x is the first camera's x axis (right in its image) made horizontal, y = z cross x (the first camera's viewing
  direction made horizontal), so the first view is seen as it was shot, only levelled;
- the origin stays the first camera's centre.

Up comes from, in this order: the map's floor plane where one lies near the Kinect accelerometer's up
(``accelerometer.txt``, :func:`up_from_accelerometer`: its axes are known only to a few degrees, docs/export.md),
else that accelerometer's up, else the dominant floor plane of the map, else two wall planes
(:func:`up_from_planes`), else the first camera (the identity). An identity transform writes every file as given,
bit for bit.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import open3d as o3d
import torch
import trimesh

from tambridge.export.config import ExportWorld
from tambridge.frontend.contract import FrontendResult
from tambridge.gaussians.model import GaussianTensors
from tambridge.geometry import transform_points
from tambridge.io.tum import KINECT_CAMERA_FROM_ACCELEROMETER, AccelerometerSamples
from tambridge.settings import Choice
from tambridge.trajectory import Trajectory

logger = logging.getLogger("tambridge.export.world")

MAX_SAMPLE_GAP_S = 0.02
"""An accelerometer sample counts only within this of a frame's timestamp (the frame's pose rotates it)."""

PLANE_DISTANCE_M = 0.02
"""RANSAC inlier distance of a plane (about the mesh's voxel)."""
PLANE_MIN_SHARE = 0.05
"""A plane needs this share of the points to count."""
MAX_PLANES = 6
PLANE_ITERATIONS = 300
PLANE_MAX_POINTS = 20000
"""Points sampled from the map for the plane search."""
FLOOR_WITHIN_DEG = 45.0
"""A floor's normal lies within this of the cameras' mean image-up (a handheld camera tilts, rarely by more)."""
FLOOR_NEAR_ACCELEROMETER_DEG = 10.0
"""A floor levels the world in place of the accelerometer where its normal lies within this of the accelerometer's up."""
PARALLEL_WITHIN_DEG = 10.0
"""Planes within this of the floor's normal are levels of it (table tops, shelves) and vote with it."""
WALLS_APART_DEG = 30.0
"""Two wall normals at least this far apart fix up as their cross product."""


class UpSource(Choice):
    """How the upright world's up was found."""

    accelerometer_floor = "accelerometer_floor"
    accelerometer = "accelerometer"
    floor_plane = "floor_plane"
    wall_planes = "wall_planes"
    first_camera = "first_camera"


@dataclasses.dataclass
class Plane:
    """A plane of the map: unit ``normal`` (3,), a point ``centre_m`` (3,) on it, ``inliers`` points within
    :data:`PLANE_DISTANCE_M`."""

    normal: np.ndarray
    centre_m: np.ndarray
    inliers: int


GLTF_FROM_UPRIGHT = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
"""glTF's axes (y up, as its specification fixes) from the upright world's (z up): ``(x, y, z) -> (x, z, -y)``."""
GLTF_FROM_FIRST_CAMERA = np.diag([1.0, -1.0, -1.0])
"""glTF's axes from the first camera's OpenCV frame (y down, z forward): the first camera then looks along glTF's
-z, as a glTF camera does."""


def gltf_from_world(up_source: UpSource) -> np.ndarray:
    """The (3, 3) rotation from the exported world that ``up_source`` says (the first camera's frame where it is
    ``first_camera``, else upright) to glTF's axes."""
    return GLTF_FROM_FIRST_CAMERA if up_source == UpSource.first_camera else GLTF_FROM_UPRIGHT


@dataclasses.dataclass
class WorldFrame:
    """The exported files' world: ``upright_from_first_camera`` (4, 4) rotation, how its up was found, and the
    ``world`` asked for. Its methods take what the run holds (first-camera world) into the exported world."""

    world: ExportWorld
    up_source: UpSource
    upright_from_first_camera: np.ndarray

    @property
    def is_identity(self) -> bool:
        return bool(np.array_equal(self.upright_from_first_camera, np.eye(4)))

    def trajectory(self, trajectory: Trajectory) -> Trajectory:
        if self.is_identity:
            return trajectory
        return Trajectory(trajectory.timestamps_s, self.upright_from_first_camera @ trajectory.world_from_camera)

    def points(self, points_m: np.ndarray) -> np.ndarray:
        """(P, 3) metres."""
        if self.is_identity:
            return points_m
        return transform_points(self.upright_from_first_camera, np.asarray(points_m, np.float64))

    def frontend_result(self, result: FrontendResult) -> FrontendResult:
        """The result with its map points in this world (what sparse_map.npz holds of it)."""
        if self.is_identity:
            return result
        return dataclasses.replace(result, map_points_world_m=self.points(result.map_points_world_m))

    def gaussians(self, gaussians: GaussianTensors) -> GaussianTensors:
        """The Gaussians' means rotated; they are isotropic, so nothing else changes."""
        if self.is_identity:
            return gaussians
        rotation = torch.as_tensor(self.upright_from_first_camera[:3, :3], dtype=gaussians.means_m.dtype,
                                   device=gaussians.means_m.device)
        return dataclasses.replace(gaussians, means_m=gaussians.means_m @ rotation.T)

    def mesh(self, mesh: trimesh.Trimesh) -> trimesh.Trimesh:
        if self.is_identity:
            return mesh
        return trimesh.Trimesh(vertices=self.points(mesh.vertices), faces=mesh.faces,
                               vertex_colors=mesh.visual.vertex_colors, process=False)

    def summary(self) -> dict:
        """metrics.json's ``world``: the frame, how up was found, the 4x4 as rows."""
        return {"frame": str(self.world), "up_source": str(self.up_source),
                "upright_from_first_camera": self.upright_from_first_camera.tolist()}


def up_from_accelerometer(samples: AccelerometerSamples, trajectory: Trajectory,
                          camera_from_accelerometer: np.ndarray = KINECT_CAMERA_FROM_ACCELEROMETER) -> np.ndarray | None:
    """Unit up (3,) in the trajectory's world: the mean of every sample within :data:`MAX_SAMPLE_GAP_S` of a frame,
    rotated into the world by that frame's pose (over a sequence the hand's accelerations average out, gravity
    stays); None when no sample lies near a frame."""
    nearest = trajectory.nearest(samples.timestamps_s)
    near = np.abs(nearest.timestamps_s - samples.timestamps_s) <= MAX_SAMPLE_GAP_S
    if not near.any():
        return None
    in_camera = samples.acceleration_mps2[near] @ np.asarray(camera_from_accelerometer, np.float64).T
    up = np.einsum("nij,nj->i", nearest.world_from_camera[near, :3, :3], in_camera)
    norm = np.linalg.norm(up)
    return up / norm if norm > 0 else None


def camera_up(world_from_camera: np.ndarray) -> np.ndarray:
    """Unit mean image-up (-y of the OpenCV camera) of poses (N, 4, 4), in their world."""
    up = -np.asarray(world_from_camera, np.float64)[:, :3, 1].sum(axis=0)
    return up / np.linalg.norm(up)


def dominant_planes(points_m: np.ndarray, seed: int = 0) -> list[Plane]:
    """Up to :data:`MAX_PLANES` planes of points (P, 3), largest first: Open3D's RANSAC (``segment_plane``, refitted
    to its inliers) on what earlier planes left; a plane holding less than :data:`PLANE_MIN_SHARE` ends the search.
    Deterministic for a ``seed`` and the set of points, whatever their order."""
    rng = np.random.default_rng(seed)
    points = np.asarray(points_m, np.float64).reshape(-1, 3)
    points = points[np.isfinite(points).all(axis=1)]
    # Sorted, so that the same points in another order (Open3D's mesh lists its vertices in no fixed one) give the
    # same planes, and a run its same files.
    points = points[np.lexsort(points.T[::-1])]
    if len(points) > PLANE_MAX_POINTS:
        points = points[np.sort(rng.choice(len(points), PLANE_MAX_POINTS, replace=False))]
    needed = max(3, PLANE_MIN_SHARE * len(points))
    planes = []
    # Open3D's RANSAC draws from its own generator: seeded, it gives the same planes for the same (sorted) points.
    o3d.utility.random.seed(int(rng.integers(0, 2**31 - 1)))
    while len(planes) < MAX_PLANES and len(points) >= needed:
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        # segment_plane refits the best sample's plane to all of its inliers (least squares) before returning.
        (a, b, c, d), inliers = cloud.segment_plane(PLANE_DISTANCE_M, 3, PLANE_ITERATIONS)
        if len(inliers) < needed:
            break
        normal = np.array([a, b, c]) / np.linalg.norm([a, b, c])
        inlier_mask = np.zeros(len(points), bool)
        inlier_mask[np.asarray(inliers)] = True
        planes.append(Plane(normal, points[inlier_mask].mean(axis=0), int(inlier_mask.sum())))
        points = points[~inlier_mask]
    return planes


def _facing(planes: list[Plane], prior_up: np.ndarray) -> list[np.ndarray]:
    """The planes' normals turned to the side of unit ``prior_up``."""
    return [plane.normal if plane.normal @ prior_up >= 0 else -plane.normal for plane in planes]


def up_from_floor(planes: list[Plane], prior_up: np.ndarray, within_deg: float) -> np.ndarray | None:
    """Unit up (3,) from the floor, or None: the largest plane whose normal lies within ``within_deg`` of
    ``prior_up``; up is the inlier-weighted mean normal of it and the planes parallel to it (table tops, shelves)."""
    prior_up = np.asarray(prior_up, np.float64) / np.linalg.norm(prior_up)
    normals = _facing(planes, prior_up)
    floors = [i for i, normal in enumerate(normals) if normal @ prior_up >= np.cos(np.radians(within_deg))]
    if not floors:
        return None
    floor = normals[max(floors, key=lambda i: planes[i].inliers)]
    level = [i for i, normal in enumerate(normals) if normal @ floor >= np.cos(np.radians(PARALLEL_WITHIN_DEG))]
    up = sum(planes[i].inliers * normals[i] for i in level)
    return up / np.linalg.norm(up)


def up_from_planes(planes: list[Plane], prior_up: np.ndarray) -> tuple[np.ndarray, UpSource] | None:
    """Unit up (3,) from the map's planes and how, or None: the floor (:func:`up_from_floor` within
    :data:`FLOOR_WITHIN_DEG` of ``prior_up``, the cameras' mean image-up); without one, the two largest walls
    (normals far enough apart) give up as their normals' cross product."""
    prior_up = np.asarray(prior_up, np.float64) / np.linalg.norm(prior_up)
    up = up_from_floor(planes, prior_up, FLOOR_WITHIN_DEG)
    if up is not None:
        return up, UpSource.floor_plane
    normals = _facing(planes, prior_up)
    walls = sorted(range(len(planes)), key=lambda i: -planes[i].inliers)
    for first, i in enumerate(walls):
        for j in walls[first + 1:]:
            up = np.cross(normals[i], normals[j])
            if np.linalg.norm(up) >= np.sin(np.radians(WALLS_APART_DEG)):
                up = up if up @ prior_up >= 0 else -up
                return up / np.linalg.norm(up), UpSource.wall_planes
    return None


def upright_from_up(up: np.ndarray) -> np.ndarray:
    """The rotation (4, 4) from the first camera's frame to the upright world of unit ``up`` (3, in the first
    camera's frame): z = up, x = the camera's x made horizontal (its z when x is vertical), y = z cross x."""
    z = np.asarray(up, np.float64) / np.linalg.norm(up)
    x = None
    for axis in np.eye(3)[[0, 2]]:
        candidate = axis - (axis @ z) * z
        if np.linalg.norm(candidate) > 1e-6:
            x = candidate / np.linalg.norm(candidate)
            break
    transform = np.eye(4)
    transform[:3, :3] = np.stack([x, np.cross(z, x), z])
    return transform


def find_world(world: ExportWorld, trajectory: Trajectory, accelerometer: AccelerometerSamples | None,
               surface_points_m: np.ndarray, seed: int = 0) -> WorldFrame:
    """The exported files' world for ``world``: up from the planes of ``surface_points_m`` (P, 3; mesh vertices or
    Gaussian means, first-camera world) and ``accelerometer`` (where given) as the module docstring orders them, else
    the first camera's frame. ``trajectory``: the run's poses (first-camera world)."""
    if world == ExportWorld.first_camera:
        return WorldFrame(world, UpSource.first_camera, np.eye(4))
    found = None
    planes = dominant_planes(surface_points_m, seed)
    if accelerometer is not None:
        up = up_from_accelerometer(accelerometer, trajectory)
        if up is None:
            logger.warning("accelerometer.txt: no sample within %.2f s of a frame; up from the map's planes instead",
                           MAX_SAMPLE_GAP_S)
        else:
            floor = up_from_floor(planes, up, FLOOR_NEAR_ACCELEROMETER_DEG)
            found = (up, UpSource.accelerometer) if floor is None else (floor, UpSource.accelerometer_floor)
    if found is None:
        found = up_from_planes(planes, camera_up(trajectory.world_from_camera))
    if found is None:
        logger.warning("no floor or walls found in the map: the exported files stay in the first camera's frame "
                       "(y down); see docs/export.md")
        return WorldFrame(world, UpSource.first_camera, np.eye(4))
    up, source = found
    tilt = np.degrees(np.arccos(np.clip(up @ np.array([0.0, -1.0, 0.0]), -1.0, 1.0)))
    logger.info("upright world from the %s: up is %.1f degrees from the first camera's image up", source, tilt)
    return WorldFrame(world, source, upright_from_up(up))
