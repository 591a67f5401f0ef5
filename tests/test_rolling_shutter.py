"""A rolling-shutter colour camera: keypoints and images moved to their frame's time against their exact twins and
global-shutter renders, the synthetic sequence's rolling shutter, the camera file's key, the frontend on a synthetic
sequence whose rows are read over 33 ms, and the mapping stage's resampled images."""

import dataclasses

import numpy as np
import pytest
import yaml

from tambridge.bridge.config import BridgeConfig
from tambridge.camera import TUM_PRESETS, find_sensor, rolling_shutter_row_times_s
from tambridge.errors import CameraConfigError, ConfigError
from tambridge.evaluation.trajectory import evaluate_trajectory
from tambridge.frontend.contract import TrackResult
from tambridge.frontend.orb.config import OrbFrontendConfig
from tambridge.frontend.orb.frontend import OrbFrontend
from tambridge.images import rgb_uint8
from tambridge.rolling_shutter import (
    camera_twist_per_s,
    image_at_frame_time,
    image_at_frame_time_reference,
    keypoints_at_frame_time,
    keypoints_at_frame_time_reference,
)
from tambridge.geometry import exp_se3, inverse, look_at
from tambridge.io.synthetic import SynthOptions, default_camera, make_room_scene, render, render_rolling_shutter, write_synthetic_sequence
from tambridge.gaussians.config import MapperConfig
from tambridge.io.tum import open_sequence
from tambridge.mapping.stage import MappingStage
from tambridge.runlog import RunLog

CAMERA = default_camera(160, 120)
# A camera moving at about 1 m/s and turning at 1 rad/s: the twist per second (rho, phi), camera(t + s)_from_camera(t)
# = exp(s twist).
TWIST_PER_S = np.array([0.6, -0.4, 0.5, 0.3, -0.9, 0.2])


def world_from_camera_at(world_from_stamp: np.ndarray, dt_s: float) -> np.ndarray:
    """The moving camera's pose ``dt_s`` after the stamp."""
    return world_from_stamp @ inverse(exp_se3(dt_s * TWIST_PER_S))


def test_row_times_put_the_middle_row_at_the_stamp():
    times = rolling_shutter_row_times_s(np.array([0.0, 60.0, 120.0]), 120, 0.03)
    np.testing.assert_allclose(times, [-0.015, 0.0, 0.015])


def test_twist_per_second_integrates_back_to_the_motion():
    current_from_previous = exp_se3(np.array([0.02, -0.01, 0.03, 0.01, 0.02, -0.015]))
    np.testing.assert_allclose(exp_se3(0.04 * camera_twist_per_s(current_from_previous, 0.04)), current_from_previous,
                               atol=1e-12)


def test_moved_keypoints_match_their_exact_twin():
    rng = np.random.default_rng(0)
    keypoints = rng.uniform([0, 0], [CAMERA.width, CAMERA.height], (300, 2))
    depth = rng.uniform(0.5, 4.0, 300)
    depth[:40] = 0.0  # no depth: the median stands in
    fast = keypoints_at_frame_time(keypoints, depth, CAMERA, TWIST_PER_S, 0.033)
    slow = keypoints_at_frame_time_reference(keypoints, depth, CAMERA, TWIST_PER_S, 0.033)
    assert np.abs(fast - keypoints).max() > 1.0  # the correction is pixels here
    np.testing.assert_allclose(fast, slow, atol=0.05)
    # A global shutter, or a still camera, moves nothing; nor does the middle row.
    np.testing.assert_allclose(keypoints_at_frame_time(keypoints, depth, CAMERA, TWIST_PER_S, 0.0), keypoints)
    np.testing.assert_allclose(keypoints_at_frame_time(keypoints, depth, CAMERA, np.zeros(6), 0.033), keypoints)
    middle = np.array([[20.0, CAMERA.height / 2], [130.0, CAMERA.height / 2]])
    np.testing.assert_allclose(keypoints_at_frame_time(middle, np.array([1.0, 2.0]), CAMERA, TWIST_PER_S, 0.033), middle)


def test_without_any_depth_only_the_rotation_moves_keypoints():
    keypoints = np.array([[10.0, 5.0], [150.0, 110.0]])
    translation_only = np.array([0.6, -0.4, 0.5, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(keypoints_at_frame_time(keypoints, np.zeros(2), CAMERA, translation_only, 0.033), keypoints)
    slow = keypoints_at_frame_time_reference(keypoints, np.zeros(2), CAMERA, TWIST_PER_S, 0.033)
    np.testing.assert_allclose(keypoints_at_frame_time(keypoints, np.zeros(2), CAMERA, TWIST_PER_S, 0.033), slow, atol=0.05)


def test_moved_keypoints_are_where_the_camera_at_the_stamp_sees_their_points():
    """Points of the synthetic room seen by a rolling shutter, each at its row's pose: moved, they land where the
    camera at the stamp projects them."""
    scene = make_room_scene()
    world_from_stamp = look_at(np.array([-0.8, -0.2, 1.4]), np.array([2.0, 0.4, 0.9]))
    _, depth = render(scene, CAMERA, world_from_stamp)
    rng = np.random.default_rng(1)
    pixels = rng.uniform([0, 0], [CAMERA.width, CAMERA.height], (200, 2))
    points_world = (world_from_stamp @ np.c_[CAMERA.backproject(pixels, depth[pixels[:, 1].astype(int), pixels[:, 0].astype(int)]),
                                             np.ones(200)].T).T[:, :3]
    seen = np.zeros_like(pixels)
    for iteration in range(3):  # each point's row time depends on where the rolling shutter sees it
        times = rolling_shutter_row_times_s(seen[:, 1] if iteration else pixels[:, 1], CAMERA.height, 0.033)
        for index, (point, dt) in enumerate(zip(points_world, times)):
            camera_from_world = inverse(world_from_camera_at(world_from_stamp, dt))
            seen[index] = CAMERA.project((camera_from_world @ np.append(point, 1.0))[:3])
    seen_depth = np.array([(inverse(world_from_camera_at(world_from_stamp, dt)) @ np.append(p, 1.0))[2]
                           for p, dt in zip(points_world, rolling_shutter_row_times_s(seen[:, 1], CAMERA.height, 0.033))])
    at_stamp = CAMERA.project((inverse(world_from_stamp) @ np.c_[points_world, np.ones(200)].T).T[:, :3])
    moved = keypoints_at_frame_time(seen, seen_depth, CAMERA, TWIST_PER_S, 0.033)
    assert np.abs(seen - at_stamp).max() > 1.0
    np.testing.assert_allclose(moved, at_stamp, atol=0.05)


def test_resampled_image_matches_its_twin_and_the_global_shutter_image():
    """A rolling-shutter render of the synthetic room, resampled to the frame's time with the stamp's depth, is the
    global-shutter render at the stamp (to the band quantisation and interpolation), far nearer than as taken."""
    scene = make_room_scene()
    world_from_stamp = look_at(np.array([-0.8, -0.2, 1.4]), np.array([2.0, 0.4, 0.9]))
    sharp, depth = render(scene, CAMERA, world_from_stamp, supersampling=3)
    rolling = rgb_uint8(render_rolling_shutter(
        lambda dt, rows: render(scene, rows, world_from_camera_at(world_from_stamp, dt), supersampling=3)[0], CAMERA,
        0.033))
    resampled = image_at_frame_time(rolling, depth, CAMERA, TWIST_PER_S, 0.033)
    np.testing.assert_allclose(resampled, image_at_frame_time_reference(rolling, depth, CAMERA, TWIST_PER_S, 0.033),
                               atol=1)
    np.testing.assert_array_equal(image_at_frame_time(rolling, depth, CAMERA, np.zeros(6), 0.033), rolling)
    inner = (slice(8, -8), slice(8, -8))  # where the border pixels are not clamped
    error_as_taken = np.abs(rolling[inner].astype(float) - rgb_uint8(sharp)[inner]).mean()
    error_resampled = np.abs(resampled[inner].astype(float) - rgb_uint8(sharp)[inner]).mean()
    assert error_resampled < 0.5 * error_as_taken


def test_rolling_shutter_render_is_bands_of_global_renders():
    scene = make_room_scene()
    world_from_camera = look_at(np.array([-0.8, -0.2, 1.4]), np.array([2.0, 0.4, 0.9]))
    still = render_rolling_shutter(lambda dt, rows: render(scene, rows, world_from_camera)[0], CAMERA, 0.033)
    np.testing.assert_allclose(still, render(scene, CAMERA, world_from_camera)[0], atol=1e-6)
    moving = render_rolling_shutter(
        lambda dt, rows: render(scene, rows, world_from_camera_at(world_from_camera, dt))[0], CAMERA, 0.033)
    first_row_pose = world_from_camera_at(world_from_camera, rolling_shutter_row_times_s(np.array([1.5]), 120, 0.033)[0])
    np.testing.assert_allclose(moving[:4], render(scene, CAMERA, first_row_pose)[0][:4], atol=1e-6)
    assert np.abs(moving - render(scene, CAMERA, world_from_camera)[0]).mean() > 0.01


def test_camera_file_gives_the_readout(tmp_path):
    write_synthetic_sequence(tmp_path / "rs", SynthOptions(frame_count=2, width=32, height=24, rolling_shutter_s=0.02))
    assert open_sequence(tmp_path / "rs").camera.rolling_shutter_s == 0.02
    assert yaml.safe_load((tmp_path / "rs" / "camera.yaml").read_text())["rolling_shutter_s"] == 0.02
    assert TUM_PRESETS["fr1"].camera.rolling_shutter_s > 0 and TUM_PRESETS["fr3"].camera.rolling_shutter_s == 0
    values = yaml.safe_load((tmp_path / "rs" / "camera.yaml").read_text())
    values["rolling_shutter_s"] = -0.01
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(values))
    with pytest.raises(CameraConfigError, match="bad.yaml: rolling_shutter_s -0.01 must be in"):
        find_sensor(tmp_path / "rs", tmp_path / "bad.yaml")
    with pytest.raises(ConfigError, match="rolling shutter readout 0.05 s"):
        SynthOptions(rolling_shutter_s=0.05)


def test_correction_lowers_the_error_of_a_rolling_shutter(tmp_path):
    """The synthetic loop (about 2 m/s) read by a rolling shutter over 33 ms: keypoints moved to the frame's time
    bring the trajectory far nearer the exact ground truth than tracking as if the shutter were global, about as
    near as tracking the same loop taken with a global shutter."""

    def ate_cm(sequence_readout_s: float, tracking_readout_s: float | None) -> float:
        folder = tmp_path / f"readout_{sequence_readout_s}"
        if not folder.exists():
            write_synthetic_sequence(folder, SynthOptions(frame_count=30, width=160, height=120, depth_noise_m=0.003,
                                                          rolling_shutter_s=sequence_readout_s))
        sequence = open_sequence(folder)
        frontend = OrbFrontend(sequence.camera, OrbFrontendConfig(depth_noise_per_m=0.003, mapping_thread=False,
                                                                  rolling_shutter_s=tracking_readout_s))
        for frame in sequence:
            frontend.track(frame)
        return 100 * evaluate_trajectory(frontend.finish().trajectory, sequence.ground_truth).ate_rmse_m

    as_global, corrected = ate_cm(0.033, 0.0), ate_cm(0.033, None)  # None: the camera file's 33 ms
    global_shutter = ate_cm(0.0, None)
    assert corrected < 0.5 * as_global
    assert corrected < 1.5 * global_shutter


def test_mapping_fits_images_resampled_by_the_tracked_motion(tmp_path):
    """The mapping stage resamples a rolling-shutter frame by its motion from the frame tracked before it (the
    ground truth here), towards the global-shutter image of its stamp; with ``mapper.rolling_shutter_images`` off,
    with a readout of 0, or for the first frame (no motion yet) it keeps the frame as recorded."""
    options = SynthOptions(frame_count=30, width=160, height=120, rolling_shutter_s=0.033)
    write_synthetic_sequence(tmp_path / "rolling", options)
    write_synthetic_sequence(tmp_path / "global", dataclasses.replace(options, rolling_shutter_s=0.0))
    rolling, global_shutter = open_sequence(tmp_path / "rolling"), open_sequence(tmp_path / "global")

    def stage_after_tracking(mapper: MapperConfig, readout_s: float) -> MappingStage:
        stage = MappingStage(rolling, mapper, BridgeConfig(enabled=False), RunLog(tmp_path / "run.log"),
                             rolling_shutter_s=readout_s)
        for index, pose in enumerate(rolling.ground_truth.world_from_camera[:3]):
            stage.on_tracked(TrackResult(index, rolling.timestamps_s[index], pose, True, False, 300), rolling[index])
        return stage

    stage = stage_after_tracking(MapperConfig(), 0.033)
    assert sorted(stage.frame_twists) == [1, 2]
    inner = (slice(8, -8), slice(8, -8))
    for index in (1, 2):
        error = lambda rgb: np.abs(rgb[inner].astype(float) - global_shutter[index].rgb[inner]).mean()  # noqa: E731
        assert error(stage.at_frame_time(rolling[index]).rgb) < 0.35 * error(rolling[index].rgb)
    np.testing.assert_array_equal(stage.at_frame_time(rolling[0]).rgb, rolling[0].rgb)
    for unchanged in (stage_after_tracking(MapperConfig(rolling_shutter_images=False), 0.033),
                      stage_after_tracking(MapperConfig(), 0.0)):
        np.testing.assert_array_equal(unchanged.at_frame_time(rolling[2]).rgb, rolling[2].rgb)
