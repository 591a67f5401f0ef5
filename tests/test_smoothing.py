"""The final trajectory's smoothing (tambridge/frontend/smoothing.py): the sparse solve against its dense twin, the
motion model's exact cases, and the error of noisy poses on a known path."""

from __future__ import annotations

import numpy as np
import pytest

from tambridge.frontend.contract import FrontendResult
from tambridge.frontend.smoothing import (
    SmoothingConfig,
    along_image_ambiguity,
    median_depth_m,
    smooth_path,
    smooth_path_reference,
    smoothed_result,
    smoothed_trajectory,
)
from tambridge.geometry import exp_so3, log_so3
from tambridge.trajectory import Trajectory


def test_sparse_solve_equals_the_dense_least_squares_with_fixed_rows():
    rng = np.random.default_rng(0)
    for _ in range(100):
        count = int(rng.integers(1, 40))
        times_s = np.cumsum(rng.uniform(0.01, 0.2, count))
        path = rng.normal(size=(count, int(rng.integers(1, 4))))
        fixed = rng.random(count) < 0.3
        sigma, acceleration_sigma = rng.uniform(0.001, 0.1), rng.uniform(0.1, 10.0)
        smoothed = smooth_path(times_s, path, fixed, sigma, acceleration_sigma)
        np.testing.assert_allclose(smoothed, smooth_path_reference(times_s, path, fixed, sigma, acceleration_sigma),
                                   rtol=1e-7, atol=1e-9)
        np.testing.assert_array_equal(smoothed[fixed], path[fixed])


def _poses(times_s: np.ndarray, positions_m: np.ndarray, rotation_vectors: np.ndarray) -> Trajectory:
    world_from_camera = np.tile(np.eye(4), (len(times_s), 1, 1))
    world_from_camera[:, :3, :3] = exp_so3(rotation_vectors)
    world_from_camera[:, :3, 3] = positions_m
    return Trajectory(times_s, world_from_camera)


def test_a_constant_velocity_path_at_uneven_times_is_left_as_it_is():
    """The motion model's null space: a camera moving and turning at constant rates has no acceleration to remove."""
    times_s = np.cumsum(np.random.default_rng(1).uniform(0.02, 0.06, 60))
    positions = np.array([0.1, -0.2, 0.3]) + np.outer(times_s, [0.3, 0.1, -0.2])
    turns = np.outer(times_s, [0.2, -0.5, 0.1])  # a fixed axis: the rotation vectors are linear in time
    trajectory = _poses(times_s, positions, turns)
    smoothed = smoothed_trajectory(trajectory, np.zeros(60, bool), np.ones(60, bool), SmoothingConfig())
    np.testing.assert_allclose(smoothed.world_from_camera, trajectory.world_from_camera, atol=1e-9)


def test_noisy_poses_on_a_smooth_path_move_towards_it_keyframes_and_untracked_frames_stay():
    rng = np.random.default_rng(2)
    times_s = np.arange(300) / 30.0
    positions = 0.3 * np.stack([np.sin(2.0 * times_s), np.cos(1.3 * times_s), 0.5 * np.sin(0.7 * times_s)], axis=1)
    turns = 0.4 * np.stack([np.sin(0.9 * times_s), np.sin(1.7 * times_s), np.cos(1.1 * times_s)], axis=1)
    truth = _poses(times_s, positions, turns)
    config = SmoothingConfig()
    noisy = _poses(times_s, positions + rng.normal(scale=config.position_sigma_m, size=positions.shape), turns)
    turned = exp_so3(rng.normal(scale=np.radians(config.rotation_sigma_deg), size=(300, 3)))
    noisy.world_from_camera[:, :3, :3] = turned @ noisy.world_from_camera[:, :3, :3]
    fixed = np.arange(300) % 8 == 0
    tracked = np.ones(300, bool)
    tracked[150] = False  # a lost frame: it splits the runs
    smoothed = smoothed_trajectory(noisy, fixed, tracked, config)

    def errors(trajectory):
        position = np.linalg.norm(trajectory.world_from_camera[:, :3, 3] - positions, axis=1)
        rotation = np.linalg.norm(log_so3(trajectory.world_from_camera[:, :3, :3]
                                          @ np.swapaxes(truth.world_from_camera[:, :3, :3], 1, 2)), axis=1)
        return np.sqrt(np.mean(position[~fixed] ** 2)), np.sqrt(np.mean(rotation[~fixed] ** 2))

    (position_before, rotation_before), (position_after, rotation_after) = errors(noisy), errors(smoothed)
    assert position_after < 0.6 * position_before, (position_before, position_after)
    assert rotation_after < 0.65 * rotation_before, (rotation_before, rotation_after)
    keep = fixed | ~tracked
    np.testing.assert_array_equal(smoothed.world_from_camera[keep], noisy.world_from_camera[keep])
    # The runs are smoothed apart: what follows the lost frame does not reach the frames before it.
    later = noisy.world_from_camera.copy()
    later[151:, :3, 3] += 0.5
    moved = smoothed_trajectory(Trajectory(times_s, later), fixed, tracked, config)
    np.testing.assert_array_equal(moved.world_from_camera[:150], smoothed.world_from_camera[:150])


@pytest.mark.slow
def test_a_run_writes_its_trajectory_smoothed_about_the_keyframes_it_lists(tmp_path, monkeypatch):
    """By default ``tambridge reconstruct`` writes what the stage gives: trajectory.txt is the frontend's result
    smoothed about the keyframes keyframes.txt lists, their rows as tracked, and on a noisy sequence its error
    against the exact ground truth is lower than the frontend's. ``--set frontend.smoothing.enabled=false`` writes
    the frontend's result as it is."""
    import pipelines.reconstruct as pipeline
    from tambridge.config import load_config
    from tambridge.evaluation.metrics import read_metrics
    from tambridge.evaluation.trajectory import evaluate_trajectory
    from tambridge.io.synthetic import SynthOptions, write_synthetic_sequence
    from tambridge.io.tum import open_sequence
    from tambridge.trajectory import read_tum_trajectory

    given = []

    def recorded(result, config, scene_depths_m):
        given.append((result, scene_depths_m))
        return smoothed_result(result, config, scene_depths_m)

    monkeypatch.setattr(pipeline, "smoothed_result", recorded)
    sequence = tmp_path / "noisy"
    write_synthetic_sequence(sequence, SynthOptions(frame_count=40, depth_noise_m=0.003, colour_noise=0.01))
    options = ["mapper.enabled=false", "mesh.enabled=false", "frontend.orb.mapping_thread=false",
               "export.world=first_camera"]
    pipeline.reconstruct(sequence, tmp_path / "run", load_config(None, options), progress=False)
    ((tracked, scene_depths_m),) = given
    written = read_tum_trajectory(tmp_path / "run" / "trajectory.txt").world_from_camera
    keyframes = read_tum_trajectory(tmp_path / "run" / "keyframes.txt")
    fixed = np.isin(tracked.trajectory.timestamps_s, keyframes.timestamps_s)
    assert 2 <= fixed.sum() < len(written) - 10
    whole = smoothed_trajectory(tracked.trajectory, fixed, tracked.tracked, SmoothingConfig())
    opened = open_sequence(sequence)
    depths_m = [median_depth_m(opened.frame_depth_m(row)) for row in range(len(written))]
    np.testing.assert_array_equal(scene_depths_m, depths_m)  # recorded while tracking, as the frames were read
    expected = along_image_ambiguity(tracked.trajectory.world_from_camera, whole.world_from_camera, depths_m)
    np.testing.assert_allclose(written, expected, atol=1e-6)
    np.testing.assert_allclose(written[fixed], tracked.trajectory.world_from_camera[fixed], atol=1e-6)
    assert np.abs(written[~fixed] - tracked.trajectory.world_from_camera[~fixed]).max() > 1e-4
    smoothed_errors = read_metrics(tmp_path / "run" / "metrics.json").trajectory
    tracked_errors = evaluate_trajectory(tracked.trajectory, opened.ground_truth, align="se3")
    assert smoothed_errors.ate_rmse_m < tracked_errors.ate_rmse_m
    assert smoothed_errors.rpe_trans_rmse_m < 0.9 * tracked_errors.rpe_trans_rmse_m

    given.clear()
    unsmoothed = load_config(None, [*options, "frontend.smoothing.enabled=false"])
    pipeline.reconstruct(sequence, tmp_path / "tracked", unsmoothed, progress=False)
    ((tracked, _),) = given
    np.testing.assert_allclose(read_tum_trajectory(tmp_path / "tracked" / "trajectory.txt").world_from_camera,
                               tracked.trajectory.world_from_camera, atol=1e-6)


def test_the_smoothed_path_turns_with_the_world_and_with_the_camera():
    """Equivariance pins the rotation conventions: turning the world (``Q R_i``) or the camera (``R_i Q``) by a large
    rotation ``Q`` turns the smoothed poses the same way (the increments are taken in the world frame and each
    frame's correction is applied on the world side)."""
    rng = np.random.default_rng(4)
    times_s = np.arange(60) / 30.0
    turns = 1.5 * np.stack([np.sin(times_s), np.cos(0.7 * times_s), np.sin(1.3 * times_s)], axis=1)
    trajectory = _poses(times_s, rng.normal(scale=0.01, size=(60, 3)), turns)
    trajectory.world_from_camera[:, :3, :3] = exp_so3(rng.normal(scale=0.003, size=(60, 3))) \
        @ trajectory.world_from_camera[:, :3, :3]
    fixed, tracked = np.arange(60) % 8 == 0, np.ones(60, bool)
    smoothed = smoothed_trajectory(trajectory, fixed, tracked, SmoothingConfig()).world_from_camera[:, :3, :3]
    turn = exp_so3(np.array([0.9, -1.7, 0.4]))
    for world_side in (True, False):
        moved = trajectory.world_from_camera.copy()
        moved[:, :3, :3] = turn @ moved[:, :3, :3] if world_side else moved[:, :3, :3] @ turn
        result = smoothed_trajectory(Trajectory(times_s, moved), fixed, tracked, SmoothingConfig()).world_from_camera
        np.testing.assert_allclose(result[:, :3, :3], turn @ smoothed if world_side else smoothed @ turn, atol=1e-9)


def test_the_result_is_smoothed_about_its_keyframes_only_when_enabled():
    rng = np.random.default_rng(5)
    times_s = np.arange(30) / 30.0
    trajectory = _poses(times_s, rng.normal(scale=0.01, size=(30, 3)), rng.normal(scale=0.01, size=(30, 3)))
    keyframes = Trajectory(times_s[::6], trajectory.world_from_camera[::6])
    result = FrontendResult(trajectory, np.ones(30, bool), keyframes, {}, {}, np.zeros((0, 3)),
                            np.zeros((0, 3), np.uint8), np.zeros(0, np.int64), {}, 0, 0, 0)
    assert smoothed_result(result, SmoothingConfig(enabled=False), np.ones(30)) is result
    # The depths count only for the change along the ambiguity.
    smoothed = smoothed_result(result, SmoothingConfig(along_image_ambiguity=False),
                               np.full(30, np.nan)).trajectory.world_from_camera
    np.testing.assert_array_equal(smoothed, smoothed_trajectory(trajectory, np.arange(30) % 6 == 0, np.ones(30, bool),
                                                                SmoothingConfig()).world_from_camera)
    np.testing.assert_array_equal(smoothed[::6], trajectory.world_from_camera[::6])
    others = np.arange(30) % 6 != 0
    assert (np.abs(smoothed[others] - trajectory.world_from_camera[others]).max(axis=(1, 2)) > 1e-6).all()

    depths_m = rng.uniform(0.5, 2.0, 30)
    depths_m[7] = np.nan  # a frame that measured no depth
    depths_m[6] = 50.0  # a keyframe's: it does not move, and its depth does not fill the others'
    along = smoothed_result(result, SmoothingConfig(), depths_m).trajectory.world_from_camera
    filled = np.where(np.isnan(depths_m), np.nanmedian(depths_m[others]), depths_m)
    np.testing.assert_allclose(along[others], along_image_ambiguity(
        trajectory.world_from_camera[others], smoothed[others], filled[others]), atol=1e-12)
    np.testing.assert_array_equal(along[::6], trajectory.world_from_camera[::6])


def test_median_depth_samples_every_fourth_pixel_and_row_and_is_nan_without_depth():
    depth_m = np.zeros((8, 8))
    depth_m[::4, ::4] = [[1.0, 3.0], [2.0, 0.0]]
    depth_m[1, 1] = 100.0  # not a sample
    assert median_depth_m(depth_m) == 2.0
    assert np.isnan(median_depth_m(np.zeros((8, 8))))


def test_a_time_that_does_not_advance_splits_the_runs_instead_of_dividing_by_zero():
    times_s = np.array([0.0, 0.03, 0.06, 0.09, 0.09, 0.12, 0.15, 0.18])
    positions = np.random.default_rng(3).normal(scale=0.01, size=(8, 3))
    trajectory = _poses(times_s, positions, np.zeros((8, 3)))
    smoothed = smoothed_trajectory(trajectory, np.zeros(8, bool), np.ones(8, bool), SmoothingConfig())
    assert np.isfinite(smoothed.world_from_camera).all()
    apart = [smoothed_trajectory(_poses(times_s[part], positions[part], np.zeros((4, 3))), np.zeros(4, bool),
                                 np.ones(4, bool), SmoothingConfig()).world_from_camera
             for part in (slice(0, 4), slice(4, 8))]
    np.testing.assert_allclose(smoothed.world_from_camera, np.concatenate(apart), atol=1e-12)


def test_along_the_image_ambiguity_a_change_keeps_the_optical_axis_point_where_the_tracked_pose_sees_it():
    """A change already along the two image-preserving motions is kept whole; any other change is cut to them, so the
    point on the tracked camera's optical axis at the scene depth lands where the tracked pose sees it (to second
    order in the change), and the change along the axis and about it is dropped."""
    from tambridge.geometry import exp_se3, inverse, log_se3

    rng = np.random.default_rng(5)
    tracked = np.stack([exp_se3(rng.normal(scale=[0.5, 0.5, 0.5, 0.4, 0.4, 0.4])) for _ in range(20)])
    depth_m = rng.uniform(0.5, 3.0, 20)
    small = 1e-3
    along = np.stack([exp_se3(small * np.array([z, -2 * z, 0.0, -2.0, -1.0, 0.0])) for z in depth_m])
    np.testing.assert_allclose(along_image_ambiguity(tracked, tracked @ along, depth_m), tracked @ along, atol=1e-12)

    smoothed = tracked @ np.stack([exp_se3(small * rng.normal(size=6)) for _ in range(20)])
    kept = along_image_ambiguity(tracked, smoothed, depth_m)
    for pose, result, moved, z in zip(tracked, kept, smoothed, depth_m):
        point_world = pose @ np.array([0.0, 0.0, z, 1.0])
        in_result, in_moved = (inverse(result) @ point_world)[:3], (inverse(moved) @ point_world)[:3]
        np.testing.assert_allclose(in_result[:2] / in_result[2], [0.0, 0.0], atol=10 * small ** 2)
        assert np.linalg.norm(in_moved[:2] / in_moved[2]) > 20 * small ** 2  # the full change does move it
        change = inverse(pose) @ result
        assert abs(change[2, 3]) < 10 * small ** 2 and abs(change[1, 0]) < 10 * small ** 2  # no step along z, no roll

    # The orthogonal projection, metres against radians: a sideways step a at depth z keeps a z^2 / (z^2 + 1) of it
    # and turns by -a z / (z^2 + 1).
    step = tracked @ np.stack([exp_se3(np.array([small, 0.0, 0.0, 0.0, 0.0, 0.0]))] * 20)
    kept = np.stack([log_se3(inverse(pose) @ result)
                     for pose, result in zip(tracked, along_image_ambiguity(tracked, step, depth_m))])
    fraction = depth_m ** 2 / (depth_m ** 2 + 1)
    np.testing.assert_allclose(kept[:, 0], small * fraction, rtol=1e-6)
    np.testing.assert_allclose(kept[:, 4], -small * fraction / depth_m, rtol=1e-6)
    np.testing.assert_allclose(kept[:, [1, 2, 3, 5]], 0.0, atol=1e-12)
