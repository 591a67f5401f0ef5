"""What the map does when a keyframe arrives: new map points from depth, point and keyframe culling, local and
global BA."""

from __future__ import annotations

from contextlib import AbstractContextManager, nullcontext

import numpy as np

from tambridge.camera import Camera
from tambridge.frontend.orb.bundle_adjustment import BundleOptions, BundleProblem, DepthPair, solve_bundle_adjustment
from tambridge.frontend.orb.dense_depth import DenseTerm
from tambridge.frontend.orb.map_matching import match_map_points
from tambridge.frontend.orb.reprojection import rgbd_observations
from tambridge.frontend.orb.slam_map import Keyframe, SlamMap
from tambridge.frontend.orb.config import OrbFrontendConfig
from tambridge.geometry import inverse, transform_points


def create_points_from_depth(slam_map: SlamMap, keyframe: Keyframe, config: OrbFrontendConfig) -> int:
    """Map points for keypoints without one that have depth (ORB-SLAM2 RGB-D): every close one (depth below
    ``close_depth_m``), and at least the ``min_new_points`` closest. Returns how many were made."""
    features = keyframe.features
    free = np.flatnonzero((keyframe.point_ids < 0) & features.has_depth)
    if free.size == 0:
        return 0
    free = free[np.argsort(features.depth_m[free], kind="stable")]
    close = features.depth_m[free] < config.close_depth_m
    chosen = free[close | (np.arange(free.size) < config.min_new_points)]
    positions = transform_points(keyframe.world_from_camera, features.points_camera_m[chosen])
    ids = slam_map.points.add(
        positions, features.descriptors[chosen], features.colours[chosen], keyframe.centre_m,
        features.octaves[chosen], keyframe.id, config.scale_factor, config.n_levels,
    )
    keyframe.point_ids[chosen] = ids
    return len(ids)


FUSE_RADIUS_PX = 3.0  # ORB-SLAM's Fuse searches 3 px (times the octave scale) around the projection
FUSE_NEIGHBOURS = 10


def fuse_matches(
    slam_map: SlamMap, keyframe: Keyframe, point_ids: np.ndarray, camera: Camera, config: OrbFrontendConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """Where ``point_ids`` project into a keyframe and match a keypoint (ORB-SLAM's Fuse, its search alone):
    ``(keypoint indices (M,), point ids (M,))``. Points the keyframe already sees are skipped. Reads the map only."""
    candidates = points_not_seen_by(slam_map, keyframe, point_ids)
    if candidates.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    keypoints, ids, _ = match_map_points(slam_map, candidates, keyframe.camera_from_world, keyframe.features,
                                         keyframe.keypoint_grid, camera, config, FUSE_RADIUS_PX)
    return keypoints, ids


def points_not_seen_by(slam_map: SlamMap, keyframe: Keyframe, point_ids: np.ndarray) -> np.ndarray:
    """The ids of ``point_ids`` that the keyframe does not observe, sorted and unique (``np.setdiff1d``'s result),
    by marking rather than sorting: fusion asks it for every neighbour of a keyframe while the next frame waits."""
    marked = np.zeros(slam_map.points.count, bool)
    marked[point_ids] = True
    marked[keyframe.point_ids[keyframe.point_ids >= 0]] = False
    return np.flatnonzero(marked)


def attach_fused(
    slam_map: SlamMap, keyframe: Keyframe, keypoints: np.ndarray, point_ids: np.ndarray, incoming_wins: bool = False,
) -> tuple[list[int], list[int]]:
    """Attach each matched point (:func:`fuse_matches`) to its keypoint: a keypoint without a point gains an
    observation; one that has another point yields a merge pair ``(old, new)``: the point with fewer observations
    goes, unless ``incoming_wins`` (loop closing keeps the loop side). Returns the merge pairs for
    :meth:`SlamMap.replace_points`."""
    if keypoints.size == 0:
        return [], []
    current = keyframe.point_ids[keypoints]
    has_point = slam_map.points.good(current)
    keyframe.point_ids[keypoints[~has_point]] = point_ids[~has_point]
    old, new = current[has_point], point_ids[has_point]
    if not incoming_wins:
        observations = slam_map.points.observations
        swap = observations[old] > observations[new]
        old, new = np.where(swap, new, old), np.where(swap, old, new)
    slam_map.drop_duplicate_observations(keyframe)
    return list(old), list(new)


def fuse_points(
    slam_map: SlamMap, keyframe: Keyframe, point_ids: np.ndarray, camera: Camera, config: OrbFrontendConfig,
    incoming_wins: bool = False,
) -> tuple[list[int], list[int]]:
    """Project ``point_ids`` into a keyframe and attach each to the keypoint it matches (ORB-SLAM's Fuse):
    :func:`fuse_matches`, then :func:`attach_fused`."""
    return attach_fused(slam_map, keyframe, *fuse_matches(slam_map, keyframe, point_ids, camera, config), incoming_wins)


def fuse_with_neighbours(slam_map: SlamMap, keyframe: Keyframe, camera: Camera, config: OrbFrontendConfig,
                         lock: AbstractContextManager = nullcontext()) -> None:
    """Fuse the new keyframe's points into its covisible keyframes and theirs into it (SearchInNeighbors),
    so that points seen from several keyframes carry all those observations and duplicates merge.

    Only the changes to the map are made while holding ``lock``: the searches and the choice of descriptors only
    read it, and read nothing that the one other thread (tracking, which holds the lock for each frame) changes
    while a keyframe is being mapped (the points' visible / found counters), so tracking goes on meanwhile. The
    result is the same with or without the lock: a neighbour's search reads nothing another neighbour's attachment
    changes.
    """
    neighbours = [slam_map.keyframes[i] for i in keyframe.best_covisible(FUSE_NEIGHBOURS)]
    neighbours = [k for k in neighbours if k.segment == keyframe.segment]
    if not neighbours:
        if config.distinctive_descriptors:
            _update_descriptors(slam_map, slam_map.good_point_ids(keyframe), lock)
        return
    into_keyframe = fuse_matches(slam_map, keyframe, slam_map.points_of(neighbours), camera, config)
    with lock:
        olds, news = attach_fused(slam_map, keyframe, *into_keyframe)
    own = slam_map.good_point_ids(keyframe)
    into_neighbours = [fuse_matches(slam_map, neighbour, own, camera, config) for neighbour in neighbours]
    with lock:
        for neighbour, matched in zip(neighbours, into_neighbours):
            o, n = attach_fused(slam_map, neighbour, *matched)
            olds += o
            news += n
        slam_map.replace_points(np.array(olds, np.int64), np.array(news, np.int64))
        slam_map.update_covisibility([keyframe] + neighbours, config.covisibility_min_shared)
    if config.distinctive_descriptors:
        _update_descriptors(slam_map, slam_map.points_of([keyframe] + neighbours), lock)


def _update_descriptors(slam_map: SlamMap, point_ids: np.ndarray, lock: AbstractContextManager) -> None:
    """Give ``point_ids`` their :meth:`SlamMap.distinctive_descriptors`, chosen without ``lock`` and written with
    it."""
    ids, descriptors = slam_map.distinctive_descriptors(point_ids)
    with lock:
        slam_map.points.descriptors[ids] = descriptors


def cull_recent_points(slam_map: SlamMap, keyframe: Keyframe) -> int:
    """ORB-SLAM's MapPointCulling over points made in the last three keyframes: bad if matched in under a quarter
    of the frames that saw them in view, or if two keyframes later no second keyframe observes them."""
    points = slam_map.points
    n = points.count
    recent = np.flatnonzero(~points.bad[:n] & (points.first_keyframe[:n] >= keyframe.id - 3))
    ratio = points.found[recent] / np.maximum(points.visible[recent], 1)
    old_enough = keyframe.id - points.first_keyframe[recent] >= 2
    bad = recent[(ratio < 0.25) | (old_enough & (points.observations[recent] < 2))]
    points.bad[bad] = True
    return len(bad)


# ORB-SLAM's KeyFrameCulling: a keyframe is redundant when over 90% of its close map points are seen by at least
# three other keyframes at the same, a finer or a one-level coarser scale.
REDUNDANT_FRACTION = 0.9
REDUNDANT_OBSERVERS = 3


def finer_observer_counts(
    point_ids: np.ndarray, octaves: np.ndarray, observed_ids: np.ndarray, observed_octaves: np.ndarray, n_points: int
) -> np.ndarray:
    """For each of ``point_ids`` (M,) (unique) seen at ``octaves`` (M,): how many of the observations
    ``(observed_ids (O,), observed_octaves (O,))`` see it at an octave at most one above its own. (M,) int64."""
    level = np.full(n_points, -1, np.int64)
    level[point_ids] = octaves
    hit = (level[observed_ids] >= 0) & (observed_octaves <= level[observed_ids] + 1)
    return np.bincount(observed_ids[hit], minlength=n_points)[point_ids]


def cull_redundant_keyframes(slam_map: SlamMap, keyframe: Keyframe, config: OrbFrontendConfig) -> list[int]:
    """ORB-SLAM's KeyFrameCulling over the keyframes covisible with the new ``keyframe``: each one whose close
    map points (depth below ``close_depth_m``) are more than :data:`REDUNDANT_FRACTION` seen by at least
    :data:`REDUNDANT_OBSERVERS` other keyframes at a similar or finer scale is culled
    (:meth:`SlamMap.cull_keyframe`) with its best covisible keyframe as parent. Never culled: the new keyframe and
    the one before it (so a keyframe event's previous keyframe is live whether mapping runs inline or in the
    thread), the first keyframe of every map segment (the gauge of BA), and the ends of loop edges and segment
    links (the pose graph's constraints). Returns the culled ids, in culling order."""
    segment_starts: dict[int, int] = {}
    for k in slam_map.keyframes:
        segment_starts.setdefault(k.segment, k.id)
    protected = {keyframe.id, keyframe.id - 1} | set(segment_starts.values())
    protected |= {k for edge in slam_map.loop_edges + slam_map.segment_links for k in edge[:2]}
    candidates = [slam_map.keyframes[i] for i in keyframe.best_covisible(len(slam_map.keyframes)) if i not in protected]
    if not candidates:
        return []
    points = slam_map.points
    live = [k for k in slam_map.keyframes if not k.culled]
    observed = [k.point_ids >= 0 for k in live]
    observed_ids = np.concatenate([k.point_ids[m] for k, m in zip(live, observed)])
    observed_octaves = np.concatenate([k.features.octaves[m] for k, m in zip(live, observed)]).astype(np.int64)
    observer = np.concatenate([np.full(int(m.sum()), k.id) for k, m in zip(live, observed)])
    culled = []
    for candidate in candidates:
        depth = candidate.features.depth_m
        close = np.flatnonzero(points.good(candidate.point_ids) & (depth > 0) & (depth < config.close_depth_m))
        parent_ids = candidate.best_covisible(1)
        if close.size == 0 or not parent_ids:
            continue
        others = observer != candidate.id
        counts = finer_observer_counts(candidate.point_ids[close], candidate.features.octaves[close].astype(np.int64),
                                       observed_ids[others], observed_octaves[others], points.count)
        if (counts >= REDUNDANT_OBSERVERS).sum() > REDUNDANT_FRACTION * close.size:
            slam_map.cull_keyframe(candidate, slam_map.keyframes[parent_ids[0]])
            keep = observer != candidate.id
            observed_ids, observed_octaves, observer = observed_ids[keep], observed_octaves[keep], observer[keep]
            culled.append(candidate.id)
    return culled


def _inv_sigma2(octaves: np.ndarray, scale_factor: float) -> np.ndarray:
    return scale_factor ** (-2.0 * octaves)


def depth_pairs(slam_map: SlamMap, cameras: list[int], variable_ids: set[int], K: np.ndarray,
                config: OrbFrontendConfig) -> tuple[DepthPair, ...]:
    """Depth edges of a BA over keyframes ``cameras`` (ids, sorted): each keyframe's depth against each of the
    ``config.ba_dense_neighbours`` previous live keyframes, where both are in the problem, one of them moves, and
    no keyframe of another segment lies between them in id order (tracking that relocalised into an earlier
    segment may have lost the camera between the two, so they need not overlap)."""
    if not config.ba_dense_depth:
        return ()
    position = {kf_id: i for i, kf_id in enumerate(cameras)}
    pairs = []
    previous: list[Keyframe] = []  # the segment's latest live keyframes, newest last
    for keyframe in slam_map.keyframes:
        if keyframe.culled or keyframe.depth_reference is None:
            continue
        if previous and previous[-1].segment != keyframe.segment:
            previous = []
        tied = [reference for reference in previous if keyframe.id in position and reference.id in position
                and (keyframe.id in variable_ids or reference.id in variable_ids)]
        for reference in tied:
            term = DenseTerm(reference.depth_reference, np.eye(4), keyframe.depth_samples_m, K,
                             config.ba_dense_depth_weight, config.dense_depth_noise_per_m,
                             config.dense_depth_huber_sigmas, config.dense_depth_max_distance_m)
            pairs.append(DepthPair(position[keyframe.id], position[reference.id], term))
        previous = (previous + [keyframe])[-config.ba_dense_neighbours:]
    return tuple(pairs)


def adjust_bundle(
    slam_map: SlamMap,
    variable: list[Keyframe],
    point_ids: np.ndarray,
    fixed_ids: set[int],
    K: np.ndarray,
    config: OrbFrontendConfig,
    iterations: int,
    lock: AbstractContextManager = nullcontext(),
) -> int:
    """BA over the ``variable`` keyframes (minus ``fixed_ids``) and the points ``point_ids``; every other keyframe
    seeing those points joins as a fixed camera. Runs half the iterations, drops the outlier observations
    (chi2 beyond the 95% quantile) from their keyframes, then runs the rest. Returns the observations dropped.

    Only the result is written back while holding ``lock``: the problem is built and solved without it, which
    needs that no other thread changes what it reads meanwhile (tracking changes only the points' visible / found
    counters while a keyframe is mapped), so tracking can go on.
    """
    points = slam_map.points
    mask = np.zeros(points.count, bool)
    mask[point_ids] = True
    seen = slam_map.observers(mask)
    variable_ids = {k.id for k in variable} - fixed_ids
    cameras = sorted(seen)
    if not variable_ids & set(cameras):
        return 0
    point_index = np.full(points.count, -1, np.int64)
    point_index[point_ids] = np.arange(len(point_ids))
    keyframes = [slam_map.keyframes[i] for i in cameras]
    obs_camera = np.concatenate([np.full(len(seen[kf_id]), i) for i, kf_id in enumerate(cameras)])
    obs_keypoint = np.concatenate([seen[kf_id] for kf_id in cameras])
    obs_kf = np.array(cameras)[obs_camera]
    keypoints = np.concatenate([k.features.keypoints_px[seen[k.id]] for k in keyframes])
    depth = np.concatenate([k.features.depth_m[seen[k.id]] for k in keyframes])
    octaves = np.concatenate([k.features.octaves[seen[k.id]] for k in keyframes])
    obs_point_id = np.concatenate([k.point_ids[seen[k.id]] for k in keyframes])
    problem = BundleProblem(
        camera_from_world=np.stack([k.camera_from_world for k in keyframes]),
        points_world=points.positions_m[point_ids].copy(),
        observation_camera=obs_camera,
        observation_point=point_index[obs_point_id],
        observations=rgbd_observations(keypoints, depth),
        inv_sigma2=_inv_sigma2(octaves, config.scale_factor),
        fixed_cameras=np.array([kf_id not in variable_ids for kf_id in cameras]),
        K=K,
        depth_noise_per_m=config.depth_noise,
        depth_pairs=depth_pairs(slam_map, cameras, variable_ids, K, config),
    )
    options = BundleOptions(iterations=max(1, iterations // 2))
    solution = solve_bundle_adjustment(problem, options)
    outliers = solution.outliers
    if outliers.any():
        keep = ~outliers
        problem = BundleProblem(
            solution.camera_from_world, solution.points_world, obs_camera[keep], problem.observation_point[keep],
            problem.observations[keep], problem.inv_sigma2[keep], problem.fixed_cameras, K, config.depth_noise,
            problem.depth_pairs,
        )
        solution = solve_bundle_adjustment(problem, BundleOptions(iterations=max(1, iterations - options.iterations)))
    with lock:
        for kf_id, keypoint, point_id in zip(obs_kf[outliers], obs_keypoint[outliers], obs_point_id[outliers]):
            keyframe = slam_map.keyframes[kf_id]
            if keyframe.point_ids[keypoint] == point_id:
                keyframe.point_ids[keypoint] = -1
        for i, keyframe in enumerate(keyframes):
            if keyframe.id in variable_ids:
                keyframe.world_from_camera = inverse(solution.camera_from_world[i])
        points.positions_m[point_ids] = solution.points_world
        if outliers.any():
            slam_map.recount_observations()
        slam_map.update_culled_poses()
    return int(outliers.sum())


def local_bundle_adjustment(
    slam_map: SlamMap, keyframe: Keyframe, K: np.ndarray, config: OrbFrontendConfig, lock: AbstractContextManager = nullcontext()
) -> int:
    """Local BA: the new keyframe and its best covisible keyframes move; the first keyframe of a segment stays.
    ``lock`` is held for the changes to the map alone, as in :func:`adjust_bundle`."""
    local = [keyframe] + [slam_map.keyframes[i] for i in keyframe.best_covisible(config.local_ba_keyframes - 1)]
    local = [k for k in local if k.segment == keyframe.segment]
    fixed = {k.id for k in local if k.id == _segment_start(slam_map, k.segment)}
    point_ids = slam_map.points_of(local)
    dropped = adjust_bundle(slam_map, local, point_ids, fixed, K, config, config.local_ba_iterations, lock)
    with lock:
        slam_map.update_covisibility(local, config.covisibility_min_shared)
    return dropped


def global_bundle_adjustment(slam_map: SlamMap, K: np.ndarray, config: OrbFrontendConfig) -> int:
    """Global BA over every keyframe and good point; the first keyframe stays fixed (the gauge)."""
    every = slam_map.keyframes
    point_ids = np.flatnonzero(~slam_map.points.bad[: slam_map.points.count] & (slam_map.points.observations[: slam_map.points.count] > 0))
    return adjust_bundle(slam_map, every, point_ids, {every[0].id}, K, config, config.global_ba_iterations)


def _segment_start(slam_map: SlamMap, segment: int) -> int:
    return next(k.id for k in slam_map.keyframes if k.segment == segment)
