"""Keyframes on revisits: a camera that goes round the same loop twice makes keyframes on its second lap only where
``keyframe_revisit_distance_m`` lets it, at the same accuracy (the rule off: about as many as on the first lap)."""

import dataclasses

import numpy as np
import pytest

from tambridge.evaluation.trajectory import ate_rmse_m
from tambridge.frontend.orb.config import OrbFrontendConfig
from tambridge.frontend.orb.frontend import OrbFrontend
from tambridge.geometry import exp_se3, inverse, rotation_angle_deg
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
    results = [frontend.track(frame) for frame in frames]
    return frontend, results, frontend.finish()


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
    (_, revisiting, _), (_, everywhere, _) = with_and_without
    first_lap, second_lap = _keyframes_per_lap(everywhere)
    assert first_lap >= 10 and second_lap >= 0.7 * first_lap, (first_lap, second_lap)
    first_lap_revisiting, second_lap_revisiting = _keyframes_per_lap(revisiting)
    # Keyframes one frame apart are within the bounds: the first lap keeps one every second or third frame.
    assert first_lap_revisiting >= FRAMES_PER_LAP // 3, first_lap_revisiting
    assert second_lap_revisiting <= 1, second_lap_revisiting


def test_revisits_without_keyframes_are_tracked_as_accurately(two_laps, with_and_without):
    _, ground_truth, _ = two_laps
    (_, results, final), (_, _, final_everywhere) = with_and_without
    assert all(r.tracked for r in results) and final.frames_lost == 0
    error_m = ate_rmse_m(final.trajectory, ground_truth)
    assert error_m < 0.02 and error_m < ate_rmse_m(final_everywhere.trajectory, ground_truth) + 0.003


def _at(world_from_camera: np.ndarray, roll_deg: float = 0.0) -> np.ndarray:
    """``camera_from_world`` (4, 4) of a camera at ``world_from_camera`` turned by ``roll_deg`` about its optical axis."""
    return inverse(world_from_camera @ exp_se3(np.array([0.0, 0.0, 0.0, 0.0, 0.0, np.radians(roll_deg)])))


def test_the_revisited_keyframe_is_the_nearest_within_both_bounds_anywhere_in_the_segment(two_laps):
    (frontend, _, _), (everywhere, _, _) = _track(two_laps, **REVISIT), _track(two_laps)
    keyframes = [k for k in frontend.map.keyframes if not k.culled]
    first = keyframes[3]
    assert frontend._revisited_keyframe(_at(first.world_from_camera)) is first
    # Within the distance but turned past the angle from every keyframe.
    assert frontend._revisited_keyframe(_at(first.world_from_camera, roll_deg=30.0)) is None
    assert frontend._revisited_keyframe(_at(first.world_from_camera, roll_deg=3.0)) is first
    # A keyframe outside the reference keyframe's local map (here of two keyframes) is found all the same.
    frontend._reference = keyframes[0]
    frontend.config = dataclasses.replace(frontend.config, local_map_keyframes=2)
    local = {k.id for k in frontend.map.local_keyframes(keyframes[0], 2)}
    apart = [k for k in keyframes if k.id not in local]
    assert apart
    for keyframe in apart:
        assert frontend._revisited_keyframe(_at(keyframe.world_from_camera)) is keyframe
    # Between two keyframes within both bounds of each: the nearest of all within them, as a loop over the keyframes
    # finds it. Keyframes the rule made lie beyond the bounds of each other; those of the run without it do not.
    frontend = everywhere
    frontend.config = dataclasses.replace(frontend.config, **REVISIT)
    keyframes = [k for k in frontend.map.keyframes if not k.culled]

    def within(keyframe, world_from_camera):
        return (np.linalg.norm(keyframe.centre_m - world_from_camera[:3, 3]) <= REVISIT["keyframe_revisit_distance_m"]
                and rotation_angle_deg(keyframe.camera_from_world @ world_from_camera) <= REVISIT["keyframe_revisit_angle_deg"])

    poses = []
    for far in keyframes:
        for near in keyframes:
            pose = near.world_from_camera.copy()
            pose[:3, 3] = 0.3 * far.centre_m + 0.7 * near.centre_m
            if far is not near and within(far, pose) and within(near, pose):
                poses.append(pose)
    assert len(poses) >= 10
    for pose in poses:
        nearest = min((k for k in keyframes if within(k, pose)), key=lambda k: np.linalg.norm(k.centre_m - pose[:3, 3]))
        assert frontend._revisited_keyframe(inverse(pose)) is nearest


def test_the_mapper_still_gets_the_keyframe_it_asks_for_on_a_revisit(two_laps):
    frames, _, camera = two_laps
    frontend = OrbFrontend(camera, OrbFrontendConfig(**SMALL_IMAGE, **REVISIT))
    asked_at = FRAMES_PER_LAP + FRAMES_PER_LAP // 2
    made = []
    for frame in frames[:asked_at + 1]:
        if frame.index == asked_at:
            frontend.request_keyframe()
        made.append(frontend.track(frame).is_keyframe)
    assert made[asked_at] and not any(made[FRAMES_PER_LAP:asked_at])
