"""The dense point-to-plane depth term of motion-only refinement: kernel against its twin, the Jacobian against
finite differences, the refinement with it, and the frontend with it on synthetic sequences."""

import dataclasses

import numpy as np
import pytest

from tambridge.evaluation.trajectory import evaluate_trajectory
from tambridge.frontend.orb.config import OrbFrontendConfig
from tambridge.frontend.orb.dense_depth import (
    DenseTerm,
    align_depth,
    dense_jacobian_reference,
    dense_normal_equations,
    dense_normal_equations_reference,
    dense_pair_cost,
    dense_pair_jacobian_reference,
    dense_pair_normal_equations,
    dense_pair_normal_equations_reference,
    dense_reference,
    dense_residuals_reference,
    dense_samples,
)
from tambridge.frontend.orb.frontend import OrbFrontend
from tambridge.frontend.orb.pose_estimation import (
    refine_camera_from_world,
    refine_camera_from_world_reference,
)
from tambridge.frontend.orb.reprojection import rgbd_observations
from tambridge.geometry import exp_se3, inverse, look_at, transform_points
from tambridge.io.synthetic import (
    RotationBursts,
    SynthOptions,
    default_camera,
    make_room_scene,
    render,
    write_synthetic_sequence,
)
from tambridge.io.tum import open_sequence

CAMERA = default_camera(80, 60)
# As tests/test_frontend_orb.py: the synthetic depth is registered and exact up to 1/5000 m steps.
SMALL_IMAGE = dict(depth_residuals=True, depth_noise_per_m=0.003)


@pytest.fixture(scope="module")
def views():
    """Two rendered views of the synthetic room a few centimetres and degrees apart: ``(world_from_reference,
    reference depth, world_from_current, current depth)``."""
    scene = make_room_scene()
    world_from_reference = look_at(np.array([-1.0, -0.5, 1.4]), np.array([2.0, 0.5, 0.8]))
    world_from_current = world_from_reference @ exp_se3(np.array([0.03, -0.02, 0.01, 0.02, -0.03, 0.01]))
    reference_depth = render(scene, CAMERA, world_from_reference)[1]
    current_depth = render(scene, CAMERA, world_from_current)[1]
    return world_from_reference, reference_depth, world_from_current, current_depth


def make_term(views, weight=100.0, huber=2.0) -> DenseTerm:
    world_from_reference, reference_depth, _, current_depth = views
    reference = dense_reference(0, reference_depth, CAMERA.K, 1, 0.1, 8.0)
    samples = dense_samples(current_depth, CAMERA.K, 2, 0.1, 8.0)
    return DenseTerm(reference, inverse(world_from_reference), samples, CAMERA.K, weight, 0.0025, huber, 0.05)


def perturbed(camera_from_world, scale, seed):
    return exp_se3(np.random.default_rng(seed).normal(0, scale, 6)) @ camera_from_world


def test_reference_normals_are_unit_and_face_the_camera(views):
    reference = dense_reference(0, views[1], CAMERA.K, 1, 0.1, 8.0)
    has = np.any(reference.normals != 0, axis=-1)
    assert has.mean() > 0.8
    assert np.allclose(np.linalg.norm(reference.normals[has], axis=1), 1.0)
    assert np.all(np.einsum("ij,ij->i", reference.normals[has], reference.points_camera_m[has]) < 0)


def test_depth_alone_recovers_a_motion_the_surface_holds_and_reports_a_plane_as_unheld(views):
    """Projective ICP from the reference's own pose (the motion unknown: 4 cm and 2 degrees) lands on the current
    view's pose; a flat wall facing the camera leaves three motions free, which the conditioning shows."""
    world_from_reference, _, world_from_current, _ = views
    alignment = align_depth(inverse(world_from_reference), make_term(views))
    error = alignment.camera_from_world @ world_from_current
    assert np.linalg.norm(error[:3, 3]) < 0.002 and np.degrees(np.arccos((np.trace(error[:3, :3]) - 1) / 2)) < 0.1
    assert alignment.associated_share > 0.8 and alignment.conditioning > 1e-3
    wall = np.full((CAMERA.height, CAMERA.width), 1.5, np.float32)
    flat = DenseTerm(dense_reference(0, wall, CAMERA.K, 1, 0.1, 8.0), np.eye(4), dense_samples(wall, CAMERA.K, 2, 0.1, 8.0),
                     CAMERA.K, 100.0, 0.0025, 2.0, 0.05)
    on_wall = align_depth(np.eye(4), flat)
    assert on_wall.associated_share > 0.9 and on_wall.conditioning < 1e-6


def test_kernel_matches_its_twin(views):
    term = make_term(views, huber=1.0)  # a low threshold puts samples on both sides of the Huber kernel
    camera_from_world = perturbed(inverse(views[2]), 0.01, seed=1)
    hessian, gradient, cost, count = dense_normal_equations(camera_from_world, term)
    hessian_ref, gradient_ref, cost_ref, count_ref = dense_normal_equations_reference(camera_from_world, term)
    assert count == count_ref > 0.5 * len(term.samples_camera_m)
    np.testing.assert_allclose(hessian, hessian_ref, rtol=1e-9, atol=1e-9 * np.abs(hessian_ref).max())
    np.testing.assert_allclose(gradient, gradient_ref, rtol=1e-9, atol=1e-9 * np.abs(gradient_ref).max())
    assert cost == pytest.approx(cost_ref, rel=1e-9)


def assert_jacobian_matches_finite_differences(jacobian, residuals_at, step=1e-6):
    """``jacobian`` (M, 6) against central differences of ``residuals_at(delta)`` (dense_residuals_reference's
    tuple after a step ``delta`` (6,)), on the samples whose association the steps leave as it was."""
    associated, normals = residuals_at(np.zeros(6))[2:4]
    for axis in range(6):
        delta = np.zeros(6)
        delta[axis] = step
        plus, minus = residuals_at(delta), residuals_at(-delta)
        # Where the step moved a sample into another cell the residual jumps: compare the others.
        same = associated & plus[2] & minus[2] & np.all(plus[3] == normals, axis=1) & np.all(minus[3] == normals, axis=1)
        assert same.mean() > 0.5
        numeric = (plus[0] - minus[0]) / (2 * step)
        np.testing.assert_allclose(jacobian[same, axis], numeric[same], atol=1e-6)


def test_jacobian_matches_finite_differences(views):
    term = make_term(views)
    camera_from_world = perturbed(inverse(views[2]), 0.01, seed=2)
    assert_jacobian_matches_finite_differences(
        dense_jacobian_reference(camera_from_world, term),
        lambda delta: dense_residuals_reference(exp_se3(delta) @ camera_from_world, term))


def test_residuals_vanish_at_the_true_pose_and_grow_away_from_it(views):
    term = make_term(views)
    true_camera_from_world = inverse(views[2])
    residual, _, associated = dense_residuals_reference(true_camera_from_world, term)[:3]
    # Exact depth: only the grid's piecewise-planar approximation of the surface remains.
    assert np.median(np.abs(residual[associated])) < 2e-3
    off = dense_residuals_reference(exp_se3(np.array([0.0, 0.0, 0.02, 0, 0, 0])) @ true_camera_from_world, term)
    assert np.median(np.abs(off[0][off[2]])) > 5 * np.median(np.abs(residual[associated]))


def test_few_matches_and_depth_refine_better_than_the_matches_alone(views):
    """Eight keypoint matches with half a pixel of noise leave the pose loose; the depth term pulls it to the true pose. The numba
    refinement and its slow twin agree with the term."""
    scene_points = transform_points(views[2], dense_samples(views[3], CAMERA.K, 9, 0.1, 8.0))[:8]
    true_camera_from_world = inverse(views[2])
    rng = np.random.default_rng(3)
    pixels = CAMERA.project(transform_points(true_camera_from_world, scene_points)) + rng.normal(0, 0.5, (8, 2))
    observations = rgbd_observations(pixels, np.zeros(8))
    inv_sigma2 = np.ones(8)
    start = perturbed(true_camera_from_world, 0.01, seed=4)
    term = make_term(views)

    def error_cm(camera_from_world):
        return 100 * np.linalg.norm((inverse(camera_from_world) @ true_camera_from_world)[:3, 3])

    alone, _ = refine_camera_from_world(start, scene_points, observations, inv_sigma2, CAMERA.K, 0.0)
    dense, inliers = refine_camera_from_world(start, scene_points, observations, inv_sigma2, CAMERA.K, 0.0, dense=term)
    twin, twin_inliers = refine_camera_from_world_reference(start, scene_points, observations, inv_sigma2, CAMERA.K, 0.0,
                                                            dense=term)
    np.testing.assert_allclose(dense, twin, atol=1e-9)
    assert np.array_equal(inliers, twin_inliers)
    assert error_cm(dense) < 0.3 < error_cm(alone)


@pytest.mark.slow
def test_fast_rotation_bursts_are_tracked(tmp_path):
    """Two bursts of 120 deg/s tilts (4 degrees a frame, with motion blur) on the synthetic loop: tracked with the
    default settings (the depth term where matches are few or the turn is fast) within the issue's bounds of ATE and largest error."""
    folder = tmp_path / "bursts"
    write_synthetic_sequence(folder, SynthOptions(
        frame_count=60, width=160, height=120, exposure_s=0.01, blur_subframes=3,
        bursts=RotationBursts(count=2, speed_deg_s=120.0, duration_s=0.6)))
    sequence = open_sequence(folder)
    frontend = OrbFrontend(sequence.camera, OrbFrontendConfig(**SMALL_IMAGE, mapping_thread=False))
    results = [frontend.track(frame) for frame in sequence]
    final = frontend.finish()
    assert all(result.tracked for result in results)
    # auto: the term is on in the bursts (and wherever the small image leaves few matches).
    assert 0 < frontend.frames_with_dense_depth < len(sequence)
    errors = evaluate_trajectory(final.trajectory, sequence.ground_truth, align="se3")
    assert errors.ate_rmse_m < 0.017
    assert errors.ate_max_m < 0.05


def test_pair_kernel_matches_its_twin_and_holds_the_motion_only_term(views):
    """Bundle adjustment's form of the term, both poses variable: the camera's block is motion-only's system."""
    term = make_term(views, huber=1.0)
    camera_from_world = perturbed(inverse(views[2]), 0.01, seed=3)
    reference_from_world = perturbed(inverse(views[0]), 0.005, seed=4)
    hessian, gradient, cost, count = dense_pair_normal_equations(camera_from_world, reference_from_world, term)
    twin = dense_pair_normal_equations_reference(camera_from_world, reference_from_world, term)
    assert count == twin[3] > 0.5 * len(term.samples_camera_m)
    np.testing.assert_allclose(hessian, twin[0], rtol=1e-9, atol=1e-9 * np.abs(twin[0]).max())
    np.testing.assert_allclose(gradient, twin[1], rtol=1e-9, atol=1e-9 * np.abs(twin[1]).max())
    assert cost == pytest.approx(twin[2], rel=1e-9)
    assert dense_pair_cost(camera_from_world, reference_from_world, term) == pytest.approx(twin[2], rel=1e-12)
    moved = dataclasses.replace(term, reference_from_world=reference_from_world)
    motion_only = dense_normal_equations(camera_from_world, moved)
    np.testing.assert_allclose(hessian[:6, :6], motion_only[0], rtol=1e-12)
    np.testing.assert_allclose(gradient[:6], motion_only[1], rtol=1e-12)


def test_pair_kernel_hands_its_associations_on_to_the_cost(views):
    """Bundle adjustment holds the associations of a linearisation through the steps it tries: the kernel writes
    the twin's, and the cost at a moved pose with them held matches the twin's with the same cells."""
    term = make_term(views, huber=1.0)
    camera_from_world = perturbed(inverse(views[2]), 0.01, seed=3)
    reference_from_world = perturbed(inverse(views[0]), 0.005, seed=4)
    cells = np.empty(len(term.samples_camera_m), np.int64)
    cost = dense_pair_normal_equations(camera_from_world, reference_from_world, term, cells)[2]
    twin_cells = dense_residuals_reference(camera_from_world, dataclasses.replace(
        term, reference_from_world=reference_from_world))[4]
    np.testing.assert_array_equal(cells, twin_cells)
    assert dense_pair_cost(camera_from_world, reference_from_world, term, cells) == pytest.approx(cost, rel=1e-12)
    moved = exp_se3(np.array([0.004, -0.003, 0.006, 0.004, 0.003, -0.002])) @ camera_from_world
    held = dense_pair_cost(moved, reference_from_world, term, cells)
    assert held == pytest.approx(dense_pair_normal_equations_reference(moved, reference_from_world, term, cells)[2],
                                 rel=1e-9)
    # Far from the linearisation most held samples fall behind the reference camera: still the twin's cost.
    far = exp_se3(np.array([0.0, 0.0, 4.0, 0.0, 0.0, 0.0])) @ camera_from_world
    assert dense_pair_cost(far, reference_from_world, term, cells) == pytest.approx(
        dense_pair_normal_equations_reference(far, reference_from_world, term, cells)[2], rel=1e-9)
    # The step moved samples into other cells: associated anew, the cost is another one.
    moved_cells = dense_residuals_reference(moved, dataclasses.replace(
        term, reference_from_world=reference_from_world))[4]
    assert (moved_cells != cells).mean() > 0.05
    assert abs(dense_pair_cost(moved, reference_from_world, term) - held) > 1e-3 * held


@pytest.mark.parametrize("cells, message", [
    (np.zeros(3, np.int64), "contiguous int64 array of"),
    (None, "must lie in"),
])
def test_held_associations_are_checked_before_the_kernel_reads_them(views, cells, message):
    """The kernel reads and writes ``cells`` unchecked: a wrong length or a cell off the grid fails first."""
    term = make_term(views)
    if cells is None:
        cells = np.full(len(term.samples_camera_m), term.reference.normals.shape[0] * term.reference.normals.shape[1])
    with pytest.raises(ValueError, match=message):
        dense_pair_cost(inverse(views[2]), inverse(views[0]), term, cells)


def test_cost_with_held_associations_has_the_kernels_gradient(views):
    """With the associations held, the cost's central differences along any direction of both poses are twice the
    kernel's gradient (cost = sum rho, g = sum rho' J r / sigma^2): the steps are judged by the cost whose
    gradient they follow."""
    term = make_term(views, huber=1.0)
    camera_from_world = perturbed(inverse(views[2]), 0.01, seed=7)
    reference_from_world = perturbed(inverse(views[0]), 0.005, seed=8)
    cells = np.empty(len(term.samples_camera_m), np.int64)
    _, gradient, _, _ = dense_pair_normal_equations(camera_from_world, reference_from_world, term, cells)
    rng = np.random.default_rng(9)
    step = 1e-6
    for _ in range(4):
        direction = rng.normal(size=12)
        direction /= np.linalg.norm(direction)

        def held_cost(sign):
            camera = exp_se3(sign * step * direction[:6]) @ camera_from_world
            reference = exp_se3(sign * step * direction[6:]) @ reference_from_world
            return dense_pair_cost(camera, reference, term, cells)

        numeric = (held_cost(1.0) - held_cost(-1.0)) / (2 * step)
        assert numeric == pytest.approx(2.0 * gradient @ direction, rel=1e-4, abs=1e-6 * np.abs(gradient).sum())


def test_pair_jacobian_of_the_reference_matches_finite_differences(views):
    term = dataclasses.replace(make_term(views), reference_from_world=perturbed(inverse(views[0]), 0.005, seed=5))
    camera_from_world = perturbed(inverse(views[2]), 0.01, seed=6)
    assert_jacobian_matches_finite_differences(
        dense_pair_jacobian_reference(camera_from_world, term)[:, 6:],
        lambda delta: dense_residuals_reference(camera_from_world, dataclasses.replace(
            term, reference_from_world=exp_se3(delta) @ term.reference_from_world)))
