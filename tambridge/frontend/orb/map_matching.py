"""Matching a frame's keypoints to map points, and camera poses from those matches.

``match_map_points`` projects map points with a pose guess and searches descriptors near the projection
(ORB-SLAM's SearchByProjection); ``localise`` needs no guess: brute-force descriptor matches to a set of map
points, PnP-RANSAC, then a projection search with the found pose (relocalisation, loop verification).
"""

from __future__ import annotations

import dataclasses

import numba
import numpy as np

from tambridge.camera import Camera, pinhole_numba
from tambridge.frontend.orb.matching import KeypointGrid, match_descriptors, search_by_projection
from tambridge.frontend.orb.features import FrameFeatures
from tambridge.frontend.orb.dense_depth import DenseTerm
from tambridge.frontend.orb.pose_estimation import refine_camera_from_world, solve_pnp_ransac
from tambridge.frontend.orb.reprojection import rgbd_observations
from tambridge.frontend.orb.slam_map import SlamMap
from tambridge.frontend.orb.config import OrbFrontendConfig
from tambridge.geometry import inverse

VIEWING_COS_MIN = 0.5  # ORB-SLAM: points seen more than 60 degrees off their mean viewing direction are skipped


@dataclasses.dataclass
class PoseFix:
    """A camera pose with the matches supporting it: keypoint indices (M,) and map point ids (M,) (inliers)."""

    camera_from_world: np.ndarray
    keypoint_indices: np.ndarray
    point_ids: np.ndarray

    @property
    def inlier_count(self) -> int:
        return len(self.point_ids)


@numba.njit(cache=True, nogil=True)
def _project_visible_kernel(positions_m, normals, min_distance_m, max_distance_m, point_ids, rotation, translation, centre,
                            fx, fy, cx, cy, width, height, log_scale, n_levels):
    n = point_ids.shape[0]
    visible = np.zeros(n, np.bool_)
    projected = np.empty((n, 2))
    octaves = np.empty(n, np.int64)
    for i in range(n):
        p = point_ids[i]
        x = positions_m[p, 0] * rotation[0, 0] + positions_m[p, 1] * rotation[0, 1] + positions_m[p, 2] * rotation[0, 2] + translation[0]
        y = positions_m[p, 0] * rotation[1, 0] + positions_m[p, 1] * rotation[1, 1] + positions_m[p, 2] * rotation[1, 2] + translation[1]
        z = positions_m[p, 0] * rotation[2, 0] + positions_m[p, 1] * rotation[2, 1] + positions_m[p, 2] * rotation[2, 2] + translation[2]
        if not z > 1e-6:
            continue
        u, v = pinhole_numba(x, y, z, fx, fy, cx, cy)
        if not (u >= 0 and u <= width - 1 and v >= 0 and v <= height - 1):
            continue
        ox, oy, oz = positions_m[p, 0] - centre[0], positions_m[p, 1] - centre[1], positions_m[p, 2] - centre[2]
        distance = np.sqrt(ox * ox + oy * oy + oz * oz)
        if not (distance >= 0.8 * min_distance_m[p] and distance <= 1.2 * max_distance_m[p]):
            continue
        if not (ox * normals[p, 0] + oy * normals[p, 1] + oz * normals[p, 2]) / max(distance, 1e-9) >= VIEWING_COS_MIN:
            continue
        visible[i] = True
        projected[i, 0], projected[i, 1] = u, v
        octave = np.ceil(np.log(max(max_distance_m[p] / max(distance, 1e-9), 1e-9)) / log_scale)
        octaves[i] = int(min(max(octave, 0.0), n_levels - 1))
    return visible, projected, octaves


def project_visible(
    slam_map: SlamMap, point_ids: np.ndarray, camera_from_world: np.ndarray, camera: Camera, config: OrbFrontendConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points of ``point_ids`` (K,) in the camera's view: ``(ids (V,), projected_px (V, 2), predicted_octaves (V,))``.

    In view means in front, inside the image, within the point's ORB scale range and at most 60 degrees
    off its mean viewing direction; the octave it should be detected at follows from its distance. A numba
    kernel (it runs over the whole local map several times per frame); :func:`project_visible_reference` is its
    slow twin.
    """
    points = slam_map.points
    visible, projected, octaves = _project_visible_kernel(
        points.positions_m, points.normals, points.min_distance_m, points.max_distance_m,
        np.ascontiguousarray(point_ids, np.int64), np.ascontiguousarray(camera_from_world[:3, :3]),
        np.ascontiguousarray(camera_from_world[:3, 3]), np.ascontiguousarray(inverse(camera_from_world)[:3, 3]),
        camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height, np.log(config.scale_factor), config.n_levels,
    )
    return point_ids[visible], projected[visible], octaves[visible]


def project_visible_reference(
    slam_map: SlamMap, point_ids: np.ndarray, camera_from_world: np.ndarray, camera: Camera, config: OrbFrontendConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Slow twin of :func:`project_visible`, in array operations."""
    points = slam_map.points
    positions = points.positions_m[point_ids]
    points_camera = positions @ camera_from_world[:3, :3].T + camera_from_world[:3, 3]
    z = points_camera[:, 2]
    projected = camera.project(points_camera, np.where(z > 1e-6, z, 1.0))
    centre = inverse(camera_from_world)[:3, 3]
    offsets = positions - centre
    distance = np.linalg.norm(offsets, axis=1)
    viewing_cos = np.einsum("ni,ni->n", offsets, points.normals[point_ids]) / np.maximum(distance, 1e-9)
    visible = (
        (z > 1e-6) & camera.in_image(projected)
        & (distance >= 0.8 * points.min_distance_m[point_ids]) & (distance <= 1.2 * points.max_distance_m[point_ids])
        & (viewing_cos >= VIEWING_COS_MIN)
    )
    ratio = points.max_distance_m[point_ids[visible]] / np.maximum(distance[visible], 1e-9)
    octaves = np.clip(np.ceil(np.log(np.maximum(ratio, 1e-9)) / np.log(config.scale_factor)), 0, config.n_levels - 1).astype(np.int64)
    return point_ids[visible], projected[visible], octaves


def match_map_points(
    slam_map: SlamMap,
    point_ids: np.ndarray,
    camera_from_world: np.ndarray,
    features: FrameFeatures,
    grid: KeypointGrid,
    camera: Camera,
    config: OrbFrontendConfig,
    radius_px: float,
    keypoint_taken: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project map points with a pose guess and match them to keypoints within ``radius_px * scale^octave``.

    Returns ``(keypoint indices (M,), matched point ids (M,), ids of the points that were in view (V,))``.
    """
    visible_ids, projected, octaves = project_visible(slam_map, point_ids, camera_from_world, camera, config)
    if len(visible_ids) == 0 or len(features) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), visible_ids
    radius = radius_px * config.scale_factor ** octaves.astype(np.float64)
    match, _ = search_by_projection(
        projected, octaves, radius, slam_map.points.descriptors[visible_ids], grid,
        features.keypoints_px, features.octaves, features.descriptors, keypoint_taken, config.max_hamming, config.ratio,
    )
    matched = match >= 0
    return match[matched], visible_ids[matched], visible_ids


def refine_with_matches(
    camera_from_world: np.ndarray,
    features: FrameFeatures,
    keypoint_indices: np.ndarray,
    point_ids: np.ndarray,
    slam_map: SlamMap,
    K: np.ndarray,
    config: OrbFrontendConfig,
    dense: DenseTerm | None = None,
) -> PoseFix:
    """Motion-only refinement on the matches (and the ``dense`` depth term, if given); the fix keeps the inliers."""
    observations = rgbd_observations(features.keypoints_px[keypoint_indices], features.depth_m[keypoint_indices])
    inv_sigma2 = config.scale_factor ** (-2.0 * features.octaves[keypoint_indices])
    camera_from_world, inliers = refine_camera_from_world(
        camera_from_world, slam_map.points.positions_m[point_ids], observations, inv_sigma2, K, config.depth_noise,
        dense=dense,
    )
    return PoseFix(camera_from_world, keypoint_indices[inliers], point_ids[inliers])


def localise(
    slam_map: SlamMap,
    features: FrameFeatures,
    grid: KeypointGrid,
    point_ids: np.ndarray,
    camera: Camera,
    config: OrbFrontendConfig,
    min_inliers: int,
    min_ransac_inliers: int | None = None,
) -> PoseFix | None:
    """Pose of a frame against map points ``point_ids`` without a prior: brute-force matching, PnP-RANSAC,
    refinement, then a projection search over the same points and a last refinement; None unless the pose keeps
    ``min_inliers``. ``min_ransac_inliers`` (default, and at most, ``min_inliers``) is the bar before the
    projection search: a blurred frame matches few points by descriptor alone, and a pose from those few finds the
    rest by projection (ORB-SLAM's relocalisation has the same two bars)."""
    min_ransac_inliers = min_inliers if min_ransac_inliers is None else min(min_ransac_inliers, min_inliers)
    if len(point_ids) < min_ransac_inliers or len(features) < min_ransac_inliers:
        return None
    query, train = match_descriptors(features.descriptors, slam_map.points.descriptors[point_ids], config.max_hamming, 0.9)
    if len(query) < min_ransac_inliers:
        return None
    K = camera.K
    camera_from_world, inliers = solve_pnp_ransac(
        slam_map.points.positions_m[point_ids[train]], features.keypoints_px[query], K, None,
        config.pnp_reprojection_px, max(200, config.pnp_iterations),
    )
    if camera_from_world is None or inliers.sum() < min_ransac_inliers:
        return None
    fix = refine_with_matches(camera_from_world, features, query[inliers], point_ids[train][inliers], slam_map, K, config)
    if fix.inlier_count < min_ransac_inliers:
        return None
    keypoints, ids, _ = match_map_points(slam_map, point_ids, fix.camera_from_world, features, grid, camera, config,
                                         config.refine_radius_px)
    if len(ids) >= min_ransac_inliers:
        refined = refine_with_matches(fix.camera_from_world, features, keypoints, ids, slam_map, K, config)
        fix = refined if refined.inlier_count >= fix.inlier_count else fix
    return fix if fix.inlier_count >= min_inliers else None
