"""Keyframes on revisits: a camera that goes round the same loop twice makes keyframes on its second lap only where
``keyframe_revisit_distance_m`` lets it, at the same accuracy (the rule off: about as many as on the first lap)."""

import numpy as np
import pytest

from tambridge.evaluation.trajectory import ate_rmse_m
from tambridge.frontend.orb.config import OrbFrontendConfig
from tambridge.frontend.orb.frontend import OrbFrontend
from tambridge.geometry import inverse, rotation_angle_deg
from tambridge.io.synthetic import default_camera, loop_path, make_room_scene, render
from tambridge.io.tum import Frame
from tambridge.trajectory import Trajectory

# As tests/test_frontend_orb.py (160x120, registered exact depth); a keyframe may come every second frame, so that a
# lap of the loop (7 cm and about 5 degrees a frame) makes enough keyframes to count.
SMALL_IMAGE = dict(depth_residuals=True, depth_noise_per_m=0.003, keyframe_min_frames=2, mapping_thread=False)
FRAMES_PER_LAP = 30
# Beyond the loop's step from one frame to the next, short of its step over two.
REVISIT = dict(keyframe_revisit_distance_m=0.09, keyframe_revisit_angle_deg=6.0)


@pytest.fixture(scope="module")
def two_laps():
    """Two laps of the synthetic loop (60 frames at 30 frames/s), the second at the first's poses."""
    scene = make_room_scene(0)
    camera = default_camera(160, 120)
    poses = np.concatenate([loop_path(FRAMES_PER_LAP)] * 2)
    frames = []
    for index, world_from_camera in enumerate(poses):
        colour, depth_m = render(scene, camera, world_from_camera)
        frames.append(Frame(index, index / 30.0, (colour * 255 + 0.5).astype(np.uint8), depth_m.astype(np.float32)))
    return frames, Trajectory(np.arange(len(poses)) / 30.0, poses), camera


def _track(two_laps, **settings):
    frames, _, camera = two_laps
    frontend = OrbFrontend(camera, OrbFrontendConfig(**SMALL_IMAGE, **settings))
    results, surfaces = [], []
    for frame in frames:
        results.append(frontend.track(frame))
        surfaces.append(frontend._dense_reference.keyframe_id)  # whose depth the next frame's depth term is against
    return frontend, results, frontend.finish(), surfaces


@pytest.fixture(scope="module")
def with_and_without(two_laps):
    return _track(two_laps, **REVISIT), _track(two_laps)


def _keyframes_per_lap(results) -> list[int]:
    return [sum(r.is_keyframe for r in results[lap * FRAMES_PER_LAP:(lap + 1) * FRAMES_PER_LAP]) for lap in (0, 1)]


def test_the_steps_of_the_loop_lie_between_the_revisit_bounds():
    """The premise of REVISIT: a frame's step is within the bounds, two frames' steps are not."""
    poses = loop_path(FRAMES_PER_LAP)
    steps = [[(np.linalg.norm(poses[(i + gap) % FRAMES_PER_LAP, :3, 3] - poses[i, :3, 3]),
               rotation_angle_deg(inverse(poses[i]) @ poses[(i + gap) % FRAMES_PER_LAP])) for i in range(FRAMES_PER_LAP)]
             for gap in (1, 2)]
    one, two = steps
    assert max(d for d, _ in one) < REVISIT["keyframe_revisit_distance_m"]
    assert max(a for _, a in one) < REVISIT["keyframe_revisit_angle_deg"]
    assert min(d for d, _ in two) > REVISIT["keyframe_revisit_distance_m"]


def test_a_second_lap_makes_keyframes_only_without_the_revisit_rule(with_and_without):
    (_, revisiting, _, _), (_, everywhere, _, _) = with_and_without
    first_lap, second_lap = _keyframes_per_lap(everywhere)
    assert first_lap >= 10 and second_lap >= 0.7 * first_lap, (first_lap, second_lap)
    first_lap_revisiting, second_lap_revisiting = _keyframes_per_lap(revisiting)
    # Keyframes one frame apart are within the bounds: the first lap keeps one every second or third frame.
    assert first_lap_revisiting >= FRAMES_PER_LAP // 3, first_lap_revisiting
    assert second_lap_revisiting <= 1, second_lap_revisiting


def test_revisits_without_keyframes_are_tracked_as_accurately(two_laps, with_and_without):
    _, ground_truth, _ = two_laps
    (frontend, results, final, surfaces), (_, _, final_everywhere, _) = with_and_without
    assert all(r.tracked for r in results) and final.frames_lost == 0
    error_m = ate_rmse_m(final.trajectory, ground_truth)
    assert error_m < 0.02 and error_m < ate_rmse_m(final_everywhere.trajectory, ground_truth) + 0.003
    # With no keyframe made, the depth term followed the camera from one first-lap keyframe's surface to the next.
    first_lap_keyframes = sum(r.is_keyframe for r in results[:FRAMES_PER_LAP])
    assert len(set(surfaces[FRAMES_PER_LAP:])) >= first_lap_keyframes // 2, surfaces
