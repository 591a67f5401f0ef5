"""ORB features, descriptor matching and motion-only pose estimation: fast kernels against slow twins, known poses."""

import numpy as np
import pytest

from tambridge.camera import Camera
from tambridge.frontend.orb.matching import (
    build_keypoint_grid,
    distinctive_indices,
    distinctive_indices_reference,
    hamming_matrix,
    hamming_matrix_reference,
    match_descriptors,
    match_descriptors_reference,
    search_by_projection,
    search_by_projection_reference,
)
from tambridge.frontend.orb.features import (
    bucket_keypoints,
    keypoint_depths,
    keypoint_depths_reference,
    level_budgets,
    lift_keypoints,
)
from tambridge.frontend.orb.pose_estimation import (
    pose_normal_equations,
    pose_normal_equations_reference,
    refine_camera_from_world,
    refine_camera_from_world_reference,
    solve_pnp_ransac,
)
from tambridge.frontend.orb.reprojection import chi2_thresholds, project_rgbd, rgbd_observations, row_weights
from tambridge.geometry import exp_se3, inverse, transform_points

K = np.array([[300.0, 0.0, 160.0], [0.0, 300.0, 120.0], [0.0, 0.0, 1.0]])


def random_descriptors(rng, n):
    return rng.integers(0, 256, (n, 32), dtype=np.uint8)


def flip_bits(rng, descriptors, probability):
    noisy = descriptors.copy()
    flips = np.packbits(rng.random((len(descriptors), 256)) < probability, axis=1)
    return noisy ^ flips


def test_distinctive_descriptor_is_the_medoid():
    rng = np.random.default_rng(3)
    # Each group: one centre descriptor and noisy copies of it (8% of bits flipped) plus an unrelated outlier;
    # the centre has the least median distance to the others, so it is chosen wherever it sits in the group.
    groups, centres, start = [], [], [0]
    for size in (1, 2, 5, 11):
        centre = random_descriptors(rng, 1)
        members = [flip_bits(rng, np.repeat(centre, max(size - 2, 0), axis=0), 0.08), random_descriptors(rng, 1)][: size]
        group = np.concatenate([centre] + members)[:size]
        order = rng.permutation(size)
        groups.append(group[order])
        centres.append(start[-1] + int(np.flatnonzero(order == 0)[0]))
        start.append(start[-1] + size)
    descriptors, group_start = np.concatenate(groups), np.array(start)
    chosen = distinctive_indices(descriptors, group_start)
    np.testing.assert_array_equal(chosen, distinctive_indices_reference(descriptors, group_start))
    # Groups of one and two have no majority: the first row wins ties.
    assert chosen[0] == 0 and chosen[1] == 1
    np.testing.assert_array_equal(chosen[2:], centres[2:])


@pytest.mark.parametrize("largest, flipped", [(12, 0.2), (250, 0.02)])
def test_distinctive_indices_match_reference_on_random_groups(largest, flipped):
    """Small groups, and the hundreds of observations a point gathers in a long session, nearly alike (many ties)."""
    rng = np.random.default_rng(4)
    sizes = rng.integers(1, largest, 40)
    group_start = np.concatenate([[0], np.cumsum(sizes)])
    descriptors = flip_bits(rng, np.repeat(random_descriptors(rng, 40), sizes, axis=0), flipped)
    np.testing.assert_array_equal(distinctive_indices(descriptors, group_start),
                                  distinctive_indices_reference(descriptors, group_start))


def test_hamming_matrix_matches_reference():
    rng = np.random.default_rng(0)
    a, b = random_descriptors(rng, 40), random_descriptors(rng, 55)
    np.testing.assert_array_equal(hamming_matrix(a, b), hamming_matrix_reference(a, b))
    assert hamming_matrix(a[:1], a[:1])[0, 0] == 0


def test_match_descriptors_matches_reference_and_finds_true_pairs():
    rng = np.random.default_rng(1)
    train = random_descriptors(rng, 300)
    truth = rng.permutation(300)[:200]
    query = flip_bits(rng, train[truth], 0.05)
    fast = match_descriptors(query, train)
    slow = match_descriptors_reference(query, train)
    order = np.argsort(fast[0])
    np.testing.assert_array_equal(fast[0][order], slow[0])
    np.testing.assert_array_equal(fast[1][order], slow[1])
    assert np.mean(truth[fast[0]] == fast[1]) == 1.0 and len(fast[0]) > 190


@pytest.mark.parametrize("seed", [2, 3])
def test_search_by_projection_matches_reference(seed):
    rng = np.random.default_rng(seed)
    n_keypoints, n_points = 400, 250
    keypoints = rng.uniform([0, 0], [320, 240], (n_keypoints, 2))
    octaves = rng.integers(0, 4, n_keypoints)
    descriptors = random_descriptors(rng, n_keypoints)
    source = rng.integers(0, n_keypoints, n_points)
    projected = keypoints[source] + rng.normal(0.0, 2.0, (n_points, 2))
    point_descriptors = flip_bits(rng, descriptors[source], 0.08)
    predicted = np.clip(octaves[source] + rng.integers(-1, 2, n_points), 0, 3)
    radius = 6.0 * 1.2 ** predicted
    taken = rng.random(n_keypoints) < 0.1
    grid = build_keypoint_grid(keypoints, 320, 240)
    fast = search_by_projection(projected, predicted, radius, point_descriptors, grid, keypoints, octaves, descriptors, taken)
    slow = search_by_projection_reference(projected, predicted, radius, point_descriptors, keypoints, octaves, descriptors, taken)
    np.testing.assert_array_equal(fast[0], slow[0])
    matched = fast[0] >= 0
    assert matched.sum() > 0.5 * n_points
    assert np.mean(fast[0][matched] == source[matched]) > 0.95
    assert not taken[fast[0][matched]].any()
    assert len(set(fast[0][matched].tolist())) == matched.sum()


def test_bucketing_keeps_the_budget_and_spreads_keypoints():
    rng = np.random.default_rng(4)
    # A dense textured blob in one corner with strong responses, weak corners elsewhere.
    corner = rng.uniform([0, 0], [120, 90], (3000, 2))
    rest = rng.uniform([0, 0], [640, 480], (1500, 2))
    points = np.concatenate([corner, rest])
    responses = np.concatenate([rng.uniform(50, 100, 3000), rng.uniform(1, 10, 1500)])
    octaves = rng.integers(0, 8, len(points))
    keep = bucket_keypoints(points, octaves, responses, 640, 480, 1000, 1.2, 8, 32)
    assert len(keep) == 1000 == level_budgets(1000, 1.2, 8).sum()
    by_strength = np.argsort(-responses)[:1000]
    in_corner = lambda idx: np.mean((points[idx, 0] < 120) & (points[idx, 1] < 90))  # noqa: E731
    assert in_corner(by_strength) > 0.95
    assert in_corner(keep) < 0.5


def test_lift_keypoints_back_projects_with_depth():
    camera = Camera(320, 240, 300.0, 300.0, 160.0, 120.0)
    depth = np.full((240, 320), 2.0, np.float32)
    depth[100, 50] = 0.0
    keypoints = np.array([[160.0, 120.0], [310.0, 20.0], [50.0, 100.0]])
    features = lift_keypoints(keypoints, np.zeros(3, np.int32), np.zeros((3, 32), np.uint8),
                              np.zeros((240, 320, 3), np.uint8), depth, camera, 0.1, 8.0)
    np.testing.assert_allclose(features.points_camera_m[0], [0.0, 0.0, 2.0])
    np.testing.assert_allclose(features.points_camera_m[1], [(310 - 160) / 300 * 2, (20 - 120) / 300 * 2, 2.0])
    assert features.depth_m[2] == 0.0 and not features.has_depth[2]


@pytest.mark.parametrize("window, ratio", [(0, np.inf), (1, 0.05), (2, 0.02)])
def test_keypoint_depths_kernel_matches_its_twin(window, ratio):
    """Steps, holes, NaN, values outside the range and pixels on the border, where the window is clipped."""
    rng = np.random.default_rng(11)
    depth = (2.0 * (1.0 + rng.normal(0.0, 0.002, (60, 80)))).astype(np.float32)
    depth[:, 40:] += np.float32(0.8)  # a depth edge down the middle
    depth[rng.random(depth.shape) < 0.05] = 0.0
    depth[rng.random(depth.shape) < 0.01] = np.nan
    depth[rng.random(depth.shape) < 0.02] = 9.5
    smooth = np.full((60, 80), 2.0, np.float32) + np.linspace(0, 0.01, 80, dtype=np.float32)
    bounds = np.full((60, 80), 8.0)  # float64, at the range's ends: the bounds are inside it
    bounds[:, :40] = 0.3
    rows = np.concatenate([rng.integers(0, 60, 400), [0, 59, 0, 59]])
    columns = np.concatenate([rng.integers(0, 80, 400), [0, 79, 79, 0]])
    for image in (depth, smooth, bounds):
        fast = keypoint_depths(image, rows, columns, 0.3, 8.0, window, ratio)
        slow = keypoint_depths_reference(image, rows, columns, 0.3, 8.0, window, ratio)
        np.testing.assert_array_equal(fast, slow)
    at_bounds = keypoint_depths(bounds, rows, columns, 0.3, 8.0, window, ratio)
    np.testing.assert_array_equal(at_bounds[columns < 40 - window], 0.3)
    np.testing.assert_array_equal(at_bounds[columns >= 40 + window], 8.0)
    none = np.zeros(0, np.int64)
    assert keypoint_depths(depth, none, none, 0.3, 8.0, window, ratio).shape == (0,)
    assert keypoint_depths_reference(depth, none, none, 0.3, 8.0, window, ratio).shape == (0,)
    assert 0 < np.count_nonzero(keypoint_depths(depth, rows, columns, 0.3, 8.0, window, ratio)) < len(rows)
    assert np.count_nonzero(keypoint_depths(smooth, rows, columns, 0.3, 8.0, window, ratio)) == len(rows)


def _scene(rng, n=300, outliers=0):
    camera_from_world = exp_se3(np.array([0.1, -0.05, 0.2, 0.05, 0.1, -0.02]))
    points_camera = rng.uniform([-1.5, -1.0, 1.0], [1.5, 1.0, 4.0], (n, 3))
    points_world = transform_points(inverse(camera_from_world), points_camera)
    pixels = project_rgbd(points_camera, K)[:, :2] + rng.normal(0.0, 0.3, (n, 2))
    pixels[:outliers] += rng.uniform(20, 60, (outliers, 2))
    depth = np.where(rng.random(n) < 0.7, points_camera[:, 2] * (1 + rng.normal(0, 0.002, n)), 0.0)
    return camera_from_world, points_world, rgbd_observations(pixels, depth)


@pytest.mark.parametrize("robust", [False, True])
def test_pose_normal_equations_match_reference(robust):
    rng = np.random.default_rng(5)
    camera_from_world, points_world, observations = _scene(rng, outliers=30)
    weights = row_weights(observations, rng.uniform(0.5, 1.0, len(points_world)), 0.003)
    active = rng.random(len(points_world)) < 0.8
    guess = exp_se3(rng.normal(0, 0.02, 6)) @ camera_from_world
    fast = pose_normal_equations(guess, points_world, observations, weights, chi2_thresholds(weights), active, robust, K)
    slow = pose_normal_equations_reference(guess, points_world, observations, weights, chi2_thresholds(weights), active, robust, K)
    for a, b in zip(fast, slow):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9)


def test_pnp_then_refinement_recovers_the_pose_and_rejects_outliers():
    rng = np.random.default_rng(6)
    camera_from_world, points_world, observations = _scene(rng, outliers=40)
    guess = exp_se3(rng.normal(0, 0.05, 6)) @ camera_from_world
    pnp_pose, pnp_inliers = solve_pnp_ransac(points_world, observations[:, :2], K, guess, 3.0, 100)
    assert pnp_pose is not None and pnp_inliers[40:].mean() > 0.9
    refined, inliers = refine_camera_from_world(pnp_pose, points_world, observations, np.ones(len(points_world)), K, 0.003)
    assert not inliers[:40].any() and inliers[40:].mean() > 0.9
    assert np.linalg.norm(inverse(refined)[:3, 3] - inverse(camera_from_world)[:3, 3]) < 0.005


def test_refinement_from_the_prior_alone_rejects_outliers_and_returns_a_rotation():
    # Tracking refines from the motion prior without PnP-RANSAC when the prior is close (ORB-SLAM's motion model);
    # the prior here is 2-3 cm / 1 degree off and its rotation slightly off SO(3), as a long chain of products is.
    rng = np.random.default_rng(7)
    camera_from_world, points_world, observations = _scene(rng, outliers=40)
    prior = exp_se3(np.array([0.02, -0.03, 0.01, 0.01, -0.015, 0.01])) @ camera_from_world
    prior[:3, :3] *= 1.0 + 1e-6
    refined, inliers = refine_camera_from_world(prior, points_world, observations, np.ones(len(points_world)), K, 0.003)
    assert not inliers[:40].any() and inliers[40:].mean() > 0.9
    assert np.linalg.norm(inverse(refined)[:3, 3] - inverse(camera_from_world)[:3, 3]) < 0.005
    np.testing.assert_allclose(refined[:3, :3] @ refined[:3, :3].T, np.eye(3), atol=1e-12)
    assert abs(np.linalg.det(refined[:3, :3]) - 1.0) < 1e-12


@pytest.mark.parametrize("depth_noise_per_m", [0.0, 0.003])
def test_refine_camera_from_world_kernel_matches_reference(depth_noise_per_m):
    rng = np.random.default_rng(9)
    camera_from_world, points_world, observations = _scene(rng, outliers=40)
    prior = exp_se3(rng.normal(0, 0.02, 6)) @ camera_from_world
    inv_sigma2 = rng.uniform(0.5, 1.0, len(points_world))
    fast, fast_inliers = refine_camera_from_world(prior, points_world, observations, inv_sigma2, K, depth_noise_per_m)
    slow, slow_inliers = refine_camera_from_world_reference(prior, points_world, observations, inv_sigma2, K, depth_noise_per_m)
    np.testing.assert_array_equal(fast_inliers, slow_inliers)
    np.testing.assert_allclose(fast, slow, atol=1e-12)


def test_project_visible_kernel_matches_reference():
    from tambridge.frontend.orb.map_matching import project_visible, project_visible_reference
    from tambridge.frontend.orb.slam_map import SlamMap
    from tambridge.frontend.orb.config import OrbFrontendConfig

    rng = np.random.default_rng(10)
    camera = Camera(320, 240, 300.0, 300.0, 160.0, 120.0)
    slam_map = SlamMap()
    # Points seen from around the origin, some behind the camera, off to the side, too near or too far.
    positions = rng.uniform([-3, -2, -1], [3, 2, 6], (2000, 3))
    slam_map.points.add(positions, random_descriptors(rng, 2000), np.zeros((2000, 3), np.uint8),
                        rng.normal(0, 0.3, 3), rng.integers(0, 8, 2000), 0, 1.2, 8)
    camera_from_world = exp_se3(rng.normal(0, 0.2, 6))
    point_ids = np.sort(rng.choice(2000, 1500, replace=False))
    fast = project_visible(slam_map, point_ids, camera_from_world, camera, OrbFrontendConfig())
    slow = project_visible_reference(slam_map, point_ids, camera_from_world, camera, OrbFrontendConfig())
    assert 100 < len(fast[0]) < 1500
    np.testing.assert_array_equal(fast[0], slow[0])
    np.testing.assert_allclose(fast[1], slow[1], rtol=1e-12)
    np.testing.assert_array_equal(fast[2], slow[2])


def test_map_points_take_the_distinctive_descriptor_of_their_observations():
    from tambridge.frontend.orb.features import FrameFeatures
    from tambridge.frontend.orb.slam_map import Keyframe, SlamMap

    rng = np.random.default_rng(8)
    slam_map = SlamMap()
    centres = random_descriptors(rng, 2)
    # Point 0 is first seen through an unusual view (30% of bits off); four later keyframes see it close to
    # its centre descriptor, one of them exactly. Point 1 is seen once and keeps its descriptor.
    first = flip_bits(rng, centres[:1], 0.3)
    ids = slam_map.points.add(np.zeros((2, 3)) + [0.0, 0.0, 2.0], np.concatenate([first, centres[1:]]),
                              np.zeros((2, 3), np.uint8), np.zeros(3), np.zeros(2, np.int64), 0, 1.2, 8)
    views = [first, centres[:1]] + [flip_bits(rng, centres[:1], 0.05) for _ in range(3)]
    for keyframe_id, descriptor in enumerate(views):
        n = 2 if keyframe_id == 0 else 1
        descriptors = np.concatenate([descriptor, centres[1:]])[:n]
        features = FrameFeatures(np.zeros((n, 2)), np.zeros(n, np.int32), descriptors, np.ones(n), np.zeros((n, 3)),
                                 np.zeros((n, 3), np.uint8))
        slam_map.keyframes.append(Keyframe(keyframe_id, keyframe_id, 0.0, np.eye(4), features, ids[:n].copy(), 0,
                                           build_keypoint_grid(features.keypoints_px, 640, 480)))
    chosen_ids, descriptors = slam_map.distinctive_descriptors(ids)
    np.testing.assert_array_equal(chosen_ids, ids)
    np.testing.assert_array_equal(descriptors, centres)
