"""Depth moved to the colour image's time: the motion over the delay, the warp against its twin and against a depth
rendered at the colour time, and the frontend on a synthetic sequence whose depth is taken after its colour."""

import dataclasses

import numpy as np
import pytest

from tambridge.errors import ConfigError
from tambridge.evaluation.trajectory import evaluate_trajectory
from tambridge.frontend.orb.config import OrbFrontendConfig
from tambridge.frontend.orb.depth_time import (
    colour_from_depth_motion,
    depth_at_colour_time,
    depth_at_colour_time_reference,
)
from tambridge.frontend.orb.frontend import OrbFrontend
from tambridge.geometry import exp_se3, inverse, look_at
from tambridge.io.synthetic import SynthOptions, default_camera, make_room_scene, render, write_synthetic_sequence
from tambridge.io.tum import open_sequence

CAMERA = default_camera(160, 120)


@pytest.fixture(scope="module")
def two_times():
    """The synthetic room's depth seen from ``world_from_depth`` and from ``world_from_colour``, 1.5 cm and 0.8
    degrees apart (the camera's motion over 15 ms at 1 m/s)."""
    scene = make_room_scene()
    world_from_depth = look_at(np.array([-0.8, -0.2, 1.4]), np.array([2.0, 0.4, 0.9]))
    world_from_colour = world_from_depth @ exp_se3(np.array([0.012, -0.006, 0.006, 0.005, -0.012, 0.004]))
    return world_from_depth, render(scene, CAMERA, world_from_depth)[1], world_from_colour, render(scene, CAMERA, world_from_colour)[1]


def test_motion_over_the_delay_scales_the_prior():
    current_from_previous = exp_se3(np.array([0.02, -0.01, 0.03, 0.01, 0.02, -0.015]))
    # Depth one frame interval before colour: the whole motion; at the colour time: none.
    np.testing.assert_allclose(colour_from_depth_motion(current_from_previous, 0.033, -0.033), current_from_previous, atol=1e-12)
    np.testing.assert_allclose(colour_from_depth_motion(current_from_previous, 0.033, 0.0), np.eye(4), atol=1e-12)
    half = colour_from_depth_motion(current_from_previous, 0.04, -0.02)
    np.testing.assert_allclose(half @ half, current_from_previous, atol=1e-12)
    # Depth after colour: the motion backwards.
    np.testing.assert_allclose(colour_from_depth_motion(current_from_previous, 0.04, 0.02), inverse(half), atol=1e-12)


def test_warp_matches_its_twin(two_times):
    world_from_depth, depth, world_from_colour, _ = two_times
    colour_from_depth = inverse(world_from_colour) @ world_from_depth
    fast = depth_at_colour_time(depth, CAMERA.K, colour_from_depth)
    slow = depth_at_colour_time_reference(depth, CAMERA.K, colour_from_depth)
    assert fast.dtype == slow.dtype == np.float32
    assert (fast > 0).mean() > 0.9
    np.testing.assert_allclose(fast, slow, atol=1e-6)
    np.testing.assert_array_equal(depth_at_colour_time(depth, CAMERA.K, np.eye(4)), depth)


def test_warped_depth_is_the_depth_seen_at_the_colour_time(two_times):
    world_from_depth, depth, world_from_colour, depth_at_colour = two_times
    warped = depth_at_colour_time(depth, CAMERA.K, inverse(world_from_colour) @ world_from_depth)
    both = (warped > 0) & (depth_at_colour > 0) & (depth > 0)
    assert both.mean() > 0.85
    before = np.median(np.abs(depth[both] - depth_at_colour[both]))
    after = np.median(np.abs(warped[both] - depth_at_colour[both]))
    assert before > 0.01
    assert after < 0.15 * before  # what is left: nearest-pixel sampling on slanted surfaces


def test_frames_carry_their_depth_stamp(tmp_path):
    folder = tmp_path / "delayed"
    write_synthetic_sequence(folder, SynthOptions(frame_count=3, width=32, height=24, depth_delay_s=-0.012))
    sequence = open_sequence(folder)
    assert [frame.depth_delay_s for frame in sequence] == pytest.approx([-0.012] * 3, abs=2e-6)
    with pytest.raises(ConfigError, match="depth delay 0.02 s"):
        SynthOptions(depth_delay_s=0.02)


def test_compensation_lowers_the_error_of_a_delayed_depth(tmp_path):
    """The synthetic loop (about 2 m/s) with each depth image taken 12 ms before its colour image: moving the depth
    to the colour time brings the trajectory nearer the exact ground truth; with no delay the setting changes
    nothing."""
    folder = tmp_path / "delayed"
    write_synthetic_sequence(folder, SynthOptions(frame_count=30, width=160, height=120, depth_noise_m=0.003,
                                                  depth_delay_s=-0.012))
    sequence = open_sequence(folder)
    frames = list(sequence)

    def trajectory(compensation: bool, frames=frames):
        frontend = OrbFrontend(sequence.camera, OrbFrontendConfig(depth_noise_per_m=0.003, mapping_thread=False,
                                                                  depth_time_compensation=compensation))
        for frame in frames:
            frontend.track(frame)
        return frontend.finish().trajectory

    off, on = (100 * evaluate_trajectory(trajectory(flag), sequence.ground_truth).ate_rmse_m for flag in (False, True))
    assert on < 0.8 * off
    undelayed = [dataclasses.replace(frame, depth_timestamp_s=None) for frame in frames[:8]]
    np.testing.assert_array_equal(trajectory(True, undelayed).world_from_camera,
                                  trajectory(False, undelayed).world_from_camera)
