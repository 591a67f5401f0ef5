"""Bundle adjustment: our Schur-reduced LM against pycolmap's Ceres BA, its numba kernels against slow twins."""

import dataclasses

import numpy as np
import pycolmap
import pytest

from tambridge.frontend.orb import bundle_adjustment
from tambridge.frontend.orb.bundle_adjustment import (
    BundleOptions,
    BundleProblem,
    DepthPair,
    _linearise_kernel,
    _reduced_system,
    bundle_cost,
    linearise_reference,
    reduced_system_reference,
    solve_bundle_adjustment,
)
from tambridge.frontend.orb.dense_depth import DenseTerm, dense_pair_normal_equations, dense_reference, dense_samples
from tambridge.frontend.orb.reprojection import chi2_thresholds, project_rgbd, rgbd_observations, row_weights
from tambridge.geometry import exp_se3, inverse, look_at, transform_points
from tambridge.io.synthetic import default_camera, make_room_scene, render

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])


def make_problem(seed=0, cameras=6, points=200, pixel_noise=0.5, depth_noise_per_m=0.0) -> tuple[BundleProblem, np.ndarray, np.ndarray]:
    """Cameras on an arc looking at a cloud of points, noisy observations, perturbed start; two cameras fixed.

    Returns ``(problem, true camera_from_world, true points)``.
    """
    rng = np.random.default_rng(seed)
    points_world = rng.uniform([-1.0, -1.0, 3.0], [1.0, 1.0, 5.0], (points, 3))
    camera_from_world = np.stack([
        inverse(look_at(np.array([0.25 * i - 0.6, 0.1 * np.sin(i), 0.0]), np.array([0.0, 0.0, 4.0]), np.array([0.0, -1.0, 0.0])))
        for i in range(cameras)
    ])
    obs_camera, obs_point, observations = [], [], []
    for c in range(cameras):
        points_camera = transform_points(camera_from_world[c], points_world)
        predicted = project_rgbd(points_camera, K)
        seen = np.flatnonzero((predicted[:, 0] > 0) & (predicted[:, 0] < 640) & (predicted[:, 1] > 0)
                              & (predicted[:, 1] < 480) & (rng.random(points) < 0.8))
        pixels = predicted[seen, :2] + rng.normal(0.0, pixel_noise, (len(seen), 2))
        depth = points_camera[seen, 2] + rng.normal(0.0, 1.0, len(seen)) * 0.003 * points_camera[seen, 2] ** 2
        observations.append(rgbd_observations(pixels, depth))
        obs_camera += [c] * len(seen)
        obs_point += list(seen)
    start = camera_from_world.copy()
    for c in range(2, cameras):
        start[c] = exp_se3(rng.normal(0.0, 0.01, 6)) @ camera_from_world[c]
    problem = BundleProblem(
        camera_from_world=start,
        points_world=points_world + rng.normal(0.0, 0.03, points_world.shape),
        observation_camera=np.array(obs_camera),
        observation_point=np.array(obs_point),
        observations=np.concatenate(observations),
        inv_sigma2=rng.choice([1.0, 1.0 / 1.44], len(obs_camera)),
        fixed_cameras=np.arange(cameras) < 2,
        K=K,
        depth_noise_per_m=depth_noise_per_m,
    )
    return problem, camera_from_world, points_world


def solve_with_pycolmap(problem: BundleProblem) -> tuple[np.ndarray, np.ndarray]:
    """The same problem through pycolmap (Ceres, trivial loss, fixed intrinsics, the same fixed cameras).

    pycolmap weighs every pixel residual by 1, so the test problem uses unit ``inv_sigma2`` for it.
    """
    reconstruction = pycolmap.Reconstruction()
    camera = pycolmap.Camera(model="PINHOLE", width=640, height=480, params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], camera_id=1)
    reconstruction.add_camera_with_trivial_rig(camera)
    point2d_index = {}
    for c, camera_from_world in enumerate(problem.camera_from_world):
        observed = np.flatnonzero(problem.observation_camera == c)
        image = pycolmap.Image(name=f"{c}.png", keypoints=problem.observations[observed, :2], camera_id=1, image_id=c + 1)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(camera_from_world[:3, :3]), camera_from_world[:3, 3])
        reconstruction.add_image_with_trivial_frame(image, pose)
        point2d_index.update({int(o): k for k, o in enumerate(observed)})
    point_ids = []
    for p, xyz in enumerate(problem.points_world):
        track = pycolmap.Track()
        for o in np.flatnonzero(problem.observation_point == p):
            track.add_element(int(problem.observation_camera[o]) + 1, point2d_index[int(o)])
        point_ids.append(reconstruction.add_point3D(xyz, track))
    config = pycolmap.BundleAdjustmentConfig()
    for c, fixed in enumerate(problem.fixed_cameras):
        config.add_image(c + 1)
        if fixed:
            config.set_constant_rig_from_world_pose(c + 1)
    config.set_constant_cam_intrinsics(1)
    options = pycolmap.BundleAdjustmentOptions(
        refine_focal_length=False, refine_principal_point=False, refine_extra_params=False, print_summary=False
    )
    for name in ("function_tolerance", "gradient_tolerance", "parameter_tolerance"):
        setattr(options.ceres.solver_options, name, 1e-12)
    pycolmap.create_default_bundle_adjuster(options, config, reconstruction).solve()
    cameras = np.stack([np.vstack([reconstruction.image(c + 1).cam_from_world().matrix(), [0.0, 0.0, 0.0, 1.0]])
                        for c in range(len(problem.camera_from_world))])
    points = np.stack([reconstruction.point3D(i).xyz for i in point_ids])
    return cameras, points


def test_matches_pycolmap_bundle_adjustment():
    problem, _, _ = make_problem()
    problem = dataclasses.replace(problem, inv_sigma2=np.ones(len(problem.inv_sigma2)))
    ours = solve_bundle_adjustment(problem, BundleOptions(iterations=30, robust=False))
    colmap_cameras, colmap_points = solve_with_pycolmap(problem)
    colmap_cost = bundle_cost(problem, colmap_cameras, colmap_points)
    assert ours.initial_cost > 50 * ours.final_cost  # the start was far from the optimum
    assert abs(ours.final_cost - colmap_cost) <= 0.01 * colmap_cost
    centres_ours = np.stack([inverse(c)[:3, 3] for c in ours.camera_from_world])
    centres_colmap = np.stack([inverse(c)[:3, 3] for c in colmap_cameras])
    assert np.abs(centres_ours - centres_colmap).max() < 1e-3
    assert np.abs(ours.points_world - colmap_points).max() < 1e-3


def test_rgbd_bundle_adjustment_recovers_the_cameras():
    problem, true_cameras, _ = make_problem(seed=1, depth_noise_per_m=0.003)
    solution = solve_bundle_adjustment(problem, BundleOptions(iterations=20))
    centre_error = [np.linalg.norm(inverse(a)[:3, 3] - inverse(b)[:3, 3]) for a, b in zip(solution.camera_from_world, true_cameras)]
    start_error = [np.linalg.norm(inverse(a)[:3, 3] - inverse(b)[:3, 3]) for a, b in zip(problem.camera_from_world, true_cameras)]
    # 0.5 px noise at 3-5 m leaves a few millimetres; the start was off by one to four centimetres.
    assert max(centre_error) < 0.01
    assert np.mean(centre_error[2:]) < 0.4 * np.mean(start_error[2:])
    assert solution.final_cost < solution.initial_cost


def test_robust_kernel_flags_gross_outliers():
    problem, _, _ = make_problem(seed=2)
    observations = problem.observations.copy()
    corrupted = np.arange(0, len(observations), 25)
    observations[corrupted, :2] += 40.0
    problem = dataclasses.replace(problem, observations=observations)
    solution = solve_bundle_adjustment(problem, BundleOptions(iterations=20))
    assert solution.outliers[corrupted].mean() > 0.95
    assert solution.outliers.sum() < 1.2 * len(corrupted)


def test_rejected_steps_count_against_the_iterations(monkeypatch):
    """Each step tried costs a reduced system: a solve whose every step raises the cost stops after ``iterations``
    steps, each more damped than the last, and keeps its start."""
    problem, _, _ = make_problem(seed=3)
    builds = []
    costs = []
    start_cost = bundle_adjustment._cost

    def counted_reduced_system(*args):
        builds.append(args[5])  # the damping it was built with
        return _reduced_system(*args)

    def cost_raised_by_any_step(*args):
        costs.append(start_cost(*args) if not costs else np.inf)
        return costs[-1]

    monkeypatch.setattr(bundle_adjustment, "_reduced_system", counted_reduced_system)
    monkeypatch.setattr(bundle_adjustment, "_cost", cost_raised_by_any_step)
    solution = solve_bundle_adjustment(problem, BundleOptions(iterations=4))
    assert len(builds) == 4
    np.testing.assert_allclose(np.diff(np.log(builds)), np.log(4.0))  # each rejection raises the damping
    assert np.array_equal(solution.camera_from_world, problem.camera_from_world)
    assert np.array_equal(solution.points_world, problem.points_world)


@pytest.mark.parametrize("robust", [False, True])
def test_linearisation_kernel_matches_reference(robust):
    problem, _, _ = make_problem(seed=3, cameras=4, points=60, depth_noise_per_m=0.003)
    problem.observations[::7, :2] += 30.0  # some observations beyond the Huber threshold
    weights = row_weights(problem.observations, problem.inv_sigma2, problem.depth_noise_per_m)
    thresholds = chi2_thresholds(weights)
    variable_index = np.where(problem.fixed_cameras, -1, np.cumsum(~problem.fixed_cameras) - 1)
    fast = _linearise_kernel(
        np.ascontiguousarray(problem.camera_from_world[:, :3, :3]), np.ascontiguousarray(problem.camera_from_world[:, :3, 3]),
        problem.points_world, problem.observation_camera, problem.observation_point, problem.observations, weights,
        thresholds, robust, variable_index, int((variable_index >= 0).sum()), K[0, 0], K[1, 1], K[0, 2], K[1, 2],
    )
    slow = linearise_reference(problem, weights, thresholds, robust, variable_index)
    for a, b in zip(fast, slow):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9)


def test_reduced_system_kernel_matches_dense_schur_complement():
    problem, _, _ = make_problem(seed=5, cameras=5, points=80, depth_noise_per_m=0.003)
    weights = row_weights(problem.observations, problem.inv_sigma2, problem.depth_noise_per_m)
    variable_index = np.where(problem.fixed_cameras, -1, np.cumsum(~problem.fixed_cameras) - 1)
    linearised = linearise_reference(problem, weights, chi2_thresholds(weights), True, variable_index)
    obs_variable = variable_index[problem.observation_camera]
    order = np.flatnonzero(obs_variable >= 0)
    order = order[np.argsort(problem.observation_point[order], kind="stable")]
    point_start = np.searchsorted(problem.observation_point[order], np.arange(len(problem.points_world) + 1))
    for damping in (0.0, 1e-4, 3.0):
        fast = _reduced_system(*linearised, damping, problem.observation_point, obs_variable, point_start, order)
        slow = reduced_system_reference(*linearised, damping, problem.observation_point, obs_variable)
        for a, b in zip(fast, slow):
            np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9 * np.abs(b).max())


def test_gradient_matches_finite_differences():
    problem, _, _ = make_problem(seed=4, cameras=3, points=30, depth_noise_per_m=0.003)
    weights = row_weights(problem.observations, problem.inv_sigma2, problem.depth_noise_per_m)
    variable_index = np.where(problem.fixed_cameras, -1, np.cumsum(~problem.fixed_cameras) - 1)
    _, b_c, _, b_p, _ = linearise_reference(problem, weights, chi2_thresholds(weights), False, variable_index)
    step = 1e-6
    camera = int(np.flatnonzero(variable_index >= 0)[0])
    for axis in range(6):
        delta = np.zeros(6)
        delta[axis] = step
        moved = problem.camera_from_world.copy()
        moved[camera] = exp_se3(delta) @ moved[camera]
        plus = bundle_cost(problem, camera_from_world=moved)
        moved[camera] = exp_se3(-delta) @ problem.camera_from_world[camera]
        minus = bundle_cost(problem, camera_from_world=moved)
        # b = -J^T W r = -d(0.5 r^T W r)/dx
        np.testing.assert_allclose(-(plus - minus) / (2 * step), b_c[variable_index[camera], axis], rtol=1e-4, atol=1e-3)
    for axis in range(3):
        moved = problem.points_world.copy()
        moved[5, axis] += step
        plus = bundle_cost(problem, points_world=moved)
        moved[5, axis] -= 2 * step
        minus = bundle_cost(problem, points_world=moved)
        np.testing.assert_allclose(-(plus - minus) / (2 * step), b_p[5, axis], rtol=1e-4, atol=1e-3)



def room_depth_edge(stride_px=2):
    """Two rendered 80x60 views of the synthetic room a few centimetres and degrees apart, and the depth term of
    the second's depth against the first's: ``(world_from_first, world_from_second, term)``."""
    camera = default_camera(80, 60)
    scene = make_room_scene()
    world_from_first = look_at(np.array([-1.0, -0.5, 1.4]), np.array([2.0, 0.5, 0.8]))
    world_from_second = world_from_first @ exp_se3(np.array([0.03, -0.02, 0.01, 0.02, -0.03, 0.01]))
    first_depth, second_depth = (render(scene, camera, pose)[1] for pose in (world_from_first, world_from_second))
    term = DenseTerm(dense_reference(0, first_depth, camera.K, 1, 0.1, 8.0), np.eye(4),
                     dense_samples(second_depth, camera.K, stride_px, 0.1, 8.0), camera.K, 300.0, 0.0025, 2.0, 0.05)
    return world_from_first, world_from_second, term


def test_a_depth_edge_pulls_a_camera_onto_the_other_cameras_depth():
    """The first view fixed, with the depth edge alone (no points) bundle adjustment brings the second from 2 cm
    and 1 degree off to within a millimetre of its true pose."""
    world_from_first, world_from_second, term = room_depth_edge()
    start = exp_se3(np.array([0.02, 0.0, -0.01, 0.01, 0.01, 0.0])) @ inverse(world_from_second)
    problem = BundleProblem(
        camera_from_world=np.stack([inverse(world_from_first), start]), points_world=np.zeros((0, 3)),
        observation_camera=np.zeros(0, np.int64), observation_point=np.zeros(0, np.int64),
        observations=np.zeros((0, 3)), inv_sigma2=np.zeros(0), fixed_cameras=np.array([True, False]), K=term.K,
        depth_noise_per_m=0.0, depth_pairs=(DepthPair(camera=1, reference=0, term=term),),
    )
    solution = solve_bundle_adjustment(problem, BundleOptions(iterations=20, robust=True))
    assert np.linalg.norm(inverse(start)[:3, 3] - world_from_second[:3, 3]) > 1e-2
    assert np.linalg.norm((solution.camera_from_world[1] @ world_from_second)[:3, 3]) < 1e-3
    assert solution.final_cost < 0.01 * solution.initial_cost


def test_steps_across_a_depth_edge_are_judged_with_the_linearisations_associations(monkeypatch):
    """With points and a depth edge, every step tried is accepted: the depth edge's samples keep the associations of
    the linearisation the step came from, and the cost a step must beat is taken with those. Associated anew at each
    trial, or compared with the cost of the previous associations, steps get rejected. The final cost is the one at
    the solution with its own associations."""
    problem, _, _ = make_problem(seed=3, depth_noise_per_m=0.02)
    problem = dataclasses.replace(problem, depth_pairs=(DepthPair(camera=3, reference=2, term=room_depth_edge()[2]),))
    linearisations, steps = [], []
    add_pairs = bundle_adjustment._add_pairs

    def counted_add_pairs(*args):
        linearisations.append(1)
        return add_pairs(*args)

    def counted_reduced_system(*args):
        steps.append(1)
        return _reduced_system(*args)

    monkeypatch.setattr(bundle_adjustment, "_add_pairs", counted_add_pairs)
    monkeypatch.setattr(bundle_adjustment, "_reduced_system", counted_reduced_system)
    solution = solve_bundle_adjustment(problem, BundleOptions(iterations=20))
    assert len(linearisations) == len(steps) >= 5
    assert solution.final_cost < 0.9 * solution.initial_cost
    for iterations in (1, 20):  # one step leaves it far from the associations it was taken with
        solution = solve_bundle_adjustment(problem, BundleOptions(iterations=iterations))
        assert solution.final_cost == pytest.approx(
            bundle_cost(problem, solution.camera_from_world, solution.points_world, robust=True), rel=1e-12)


def test_depth_edges_add_their_cost_to_the_points():
    problem, _, _ = make_problem(seed=3, depth_noise_per_m=0.02)
    term = room_depth_edge()[2]
    with_edge = dataclasses.replace(problem, depth_pairs=(DepthPair(camera=3, reference=2, term=term),))
    edge = dense_pair_normal_equations(problem.camera_from_world[3], problem.camera_from_world[2], term)[2]
    assert edge > 0
    assert bundle_cost(with_edge, robust=True) == pytest.approx(bundle_cost(problem, robust=True) + 0.5 * edge, rel=1e-12)


@pytest.mark.parametrize("neighbours, expected", [(1, {(2, 1), (4, 3)}), (2, {(2, 1), (2, 0), (4, 3)})])
def test_depth_edges_tie_a_keyframe_to_its_segments_previous_live_keyframes(neighbours, expected):
    """Keyframes 0-3 in segment 0 (2 culled), 4-5 in segment 1; keyframes 3-5 move. Edges, as (camera, reference)
    positions in the problem's sorted camera list, skip the culled one, never cross segments and need a moving end."""
    from tambridge.frontend.orb.config import OrbFrontendConfig
    from tambridge.frontend.orb.features import FrameFeatures
    from tambridge.frontend.orb.local_mapping import depth_pairs
    from tambridge.frontend.orb.matching import build_keypoint_grid
    from tambridge.frontend.orb.slam_map import Keyframe, SlamMap

    term = room_depth_edge()[2]
    slam_map = SlamMap()
    for keyframe_id in range(6):
        keyframe = Keyframe(keyframe_id, keyframe_id, 0.0, np.eye(4), FrameFeatures.empty(), np.zeros(0, np.int64),
                            segment=int(keyframe_id >= 4), keypoint_grid=build_keypoint_grid(np.zeros((0, 2)), 640, 480),
                            depth_reference=term.reference,
                            depth_samples_m=term.samples_camera_m, parent=0 if keyframe_id == 2 else -1)
        slam_map.keyframes.append(keyframe)
    config = OrbFrontendConfig(ba_dense_neighbours=neighbours)
    cameras = [0, 1, 3, 4, 5]
    pairs = depth_pairs(slam_map, cameras, {3, 4, 5}, term.K, config)
    assert {(pair.camera, pair.reference) for pair in pairs} == expected
    assert all(pair.term.weight == config.ba_dense_depth_weight for pair in pairs)
