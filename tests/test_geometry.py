import numpy as np
import pytest

from tambridge.geometry import (exp_se3, exp_se3_numba, exp_se3_torch, inverse, log_se3, look_at, poses_from_tum,
                                rotation_angle_deg, rotation_angles_deg, tum_from_pose)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 0.3, 3.0])
def test_exp_log_round_trip(angle):
    rng = np.random.default_rng(1)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    twist = np.concatenate([rng.normal(size=3), axis * angle])
    transform = exp_se3(twist)
    np.testing.assert_allclose(transform[:3, :3] @ transform[:3, :3].T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(log_se3(transform), twist, atol=1e-9)


@pytest.mark.parametrize("angle", [0.0, 0.01, 0.3, 3.0, np.pi])
def test_rotation_angle_is_the_angle_the_rotation_was_made_with(angle):
    axis = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
    transform = exp_se3(np.concatenate([[0.1, 0.2, 0.3], axis * angle]))
    assert rotation_angle_deg(transform) == pytest.approx(np.degrees(angle), abs=1e-5)
    assert rotation_angle_deg(transform[:3, :3]) == rotation_angle_deg(inverse(transform))


def test_rotation_angles_of_a_stack_are_each_transforms_angle():
    rng = np.random.default_rng(5)
    transforms = np.stack([exp_se3(rng.normal(size=6)) for _ in range(6)]).reshape(2, 3, 4, 4)
    angles = rotation_angles_deg(transforms)
    assert angles.shape == (2, 3)
    np.testing.assert_array_equal(angles.ravel(), [rotation_angle_deg(t) for t in transforms.reshape(6, 4, 4)])
    np.testing.assert_array_equal(rotation_angles_deg(transforms[..., :3, :3]), angles)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-3, 0.3, 3.0])
def test_numba_and_torch_exp_match_numpy(angle):
    import torch

    rng = np.random.default_rng(2)
    axis = rng.normal(size=3)
    twist = np.concatenate([rng.normal(size=3), axis / np.linalg.norm(axis) * angle])
    np.testing.assert_allclose(exp_se3_numba(twist), exp_se3(twist), rtol=0, atol=1e-14)
    np.testing.assert_allclose(exp_se3_torch(torch.from_numpy(twist)).numpy(), exp_se3(twist), rtol=0, atol=1e-12)


def test_exp_matches_matrix_exponential():
    from scipy.linalg import expm

    twist = np.array([0.1, -0.2, 0.3, 0.4, -0.1, 0.2])
    generator = np.zeros((4, 4))
    generator[:3, :3] = np.array([[0, -twist[5], twist[4]], [twist[5], 0, -twist[3]], [-twist[4], twist[3], 0]])
    generator[:3, 3] = twist[:3]
    np.testing.assert_allclose(exp_se3(twist), expm(generator), atol=1e-12)


def test_inverse_and_tum_round_trip():
    transform = exp_se3(np.array([0.5, 0.1, -0.3, 0.2, 0.7, -0.4]))
    np.testing.assert_allclose(inverse(transform) @ transform, np.eye(4), atol=1e-12)
    position, quaternion = tum_from_pose(transform)
    assert quaternion[3] >= 0
    np.testing.assert_allclose(poses_from_tum(position, quaternion), transform, atol=1e-12)


def test_poses_from_tum_converts_a_stack_as_one_at_a_time():
    transforms = np.stack([exp_se3(np.random.default_rng(i).normal(0.0, 1.0, 6)) for i in range(5)])
    positions, quaternions = zip(*(tum_from_pose(t) for t in transforms))
    stacked = poses_from_tum(np.reshape(positions, (5, 1, 3)), np.reshape(quaternions, (5, 1, 4)))
    assert stacked.shape == (5, 1, 4, 4)
    np.testing.assert_allclose(stacked[:, 0], transforms, atol=1e-12)


def test_look_at_points_the_optical_axis_at_the_target():
    world_from_camera = look_at(np.array([1.0, 2.0, 1.5]), np.array([3.0, 2.0, 1.5]))
    target_camera = inverse(world_from_camera) @ np.array([3.0, 2.0, 1.5, 1.0])
    np.testing.assert_allclose(target_camera[:3], [0.0, 0.0, 2.0], atol=1e-12)
    # Image "down" (camera +y) is world -z when up is +z.
    np.testing.assert_allclose(world_from_camera[:3, 1], [0.0, 0.0, -1.0], atol=1e-12)


def test_nearest_rotation_of_a_sum_is_the_rotation_the_pairs_lie_about():
    """Rotations in pairs R0 exp(+d) and R0 exp(-d) (d differing by pair) have R0 as their chordal mean; a reflection
    in the sum's SVD is refused (det +1)."""
    from tambridge.geometry import exp_so3, nearest_rotation

    rng = np.random.default_rng(3)
    centre = exp_so3(np.array([0.4, -1.1, 0.7]))
    offsets = rng.normal(scale=0.3, size=(6, 3))
    rotations = centre @ exp_so3(np.concatenate([offsets, -offsets]))
    np.testing.assert_allclose(nearest_rotation(rotations.sum(axis=0)), centre, atol=1e-12)
    mirrored = np.diag([1.0, 1.0, -1.0])
    assert np.linalg.det(nearest_rotation(mirrored)) == pytest.approx(1.0)


def test_rotation_onto_recovers_the_rotation_between_two_sets_of_rotations():
    from tambridge.geometry import exp_so3, rotation_onto

    rng = np.random.default_rng(8)
    rotations = exp_so3(rng.normal(size=(10, 3)))
    turn = exp_so3(np.array([-0.3, 2.1, 0.5]))
    np.testing.assert_allclose(rotation_onto(turn @ rotations, rotations), turn, atol=1e-12)
