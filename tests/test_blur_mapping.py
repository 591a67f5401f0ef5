"""Blur-aware mapping: the exposure path (SE(3) interpolation), its render count, and a map fitted to blurred
frames through it that comes out sharper than one fitted without it."""

import dataclasses

import numpy as np
import pytest
import scipy.linalg
import torch

from tambridge.bridge.blur import exposure_path, subpose_count
from tambridge.bridge.config import BridgeConfig
from tambridge.config import load_config
from tambridge.errors import ConfigError
from tambridge.evaluation.rendering import psnr_db
from tambridge.frontend.contract import TrackResult
from tambridge.gaussians.config import MapperConfig
from tambridge.gaussians.mapper import GaussianMap, ViewImages, render_exposure
from tambridge.geometry import exp_se3, inverse, poses_along
from tambridge.io.synthetic import SynthOptions, default_camera, look_at, make_room_scene, render, write_synthetic_sequence
from tambridge.io.tum import open_sequence
from tambridge.mapping.stage import MappingStage, blur_exposure_s, round_robin
from tambridge.runlog import RunLog
from tambridge.threads import TORCH_THREADS, compute_threads
from tests.test_mapper import GroundTruthFrontend


@pytest.fixture(autouse=True)
def one_thread_each():
    with compute_threads(TORCH_THREADS, 1):
        yield


def geodesic_twin(pose_a, pose_b, fraction):
    """The obvious SE(3) geodesic: matrix exponential of the matrix logarithm, scaled."""
    return pose_a @ scipy.linalg.expm(fraction * scipy.linalg.logm(np.linalg.inv(pose_a) @ pose_b).real)


def test_poses_along_matches_the_matrix_exponential_twin_between_and_beyond_the_poses():
    rng = np.random.default_rng(3)
    poses = np.stack([exp_se3(rng.normal(0, 0.4, 6)) for _ in range(3)])
    times = np.array([-0.04, 0.0, 0.03])
    queries = np.array([-0.07, -0.04, -0.01, 0.0, 0.02, 0.03, 0.05])
    got = poses_along(times, poses, queries)
    for query, pose in zip(queries, got):
        segment = 0 if query < 0 else 1
        fraction = (query - times[segment]) / (times[segment + 1] - times[segment])
        np.testing.assert_allclose(pose, geodesic_twin(poses[segment], poses[segment + 1], fraction), atol=1e-9)


def test_a_constant_twist_path_is_recovered_exactly_from_two_poses():
    base, twist = exp_se3(np.array([0.3, -0.2, 1.0, 0.1, 0.5, -0.2])), np.array([0.4, 0.1, -0.3, 0.5, -1.2, 2.0])
    path = lambda t: base @ exp_se3(t * twist)  # noqa: E731 (velocity ``twist`` per second, body frame)
    got = poses_along(np.array([-1 / 30, 0.0]), np.stack([path(-1 / 30), path(0.0)]), np.array([-0.02, 0.01, 0.016]))
    for time, pose in zip([-0.02, 0.01, 0.016], got):
        np.testing.assert_allclose(pose, path(time), atol=1e-12)


def test_the_exposure_path_runs_through_both_neighbours_and_the_render_count_follows_the_image_motion():
    camera = default_camera(64, 48)
    frame = exp_se3(np.array([0.1, 0.2, 0.3, 0.0, 0.2, 0.0]))
    step = np.eye(4)
    step[0, 3] = 0.03  # 3 cm to the right per frame: on a wall 2 m away the image moves f * 0.03 / 2 px per frame
    path = exposure_path(frame, 10.0, [(10.0 - 1 / 30, frame @ inverse(step)), (10.0 + 1 / 30, frame @ step)], 1 / 30)
    start, middle, end = path.poses(3)
    np.testing.assert_allclose(middle, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(end[:3, 3], [0.03 / 3, 0, 0], atol=1e-12)  # the middle of the last third of [-e/2, e/2]
    np.testing.assert_allclose(start[:3, 3], [-0.03 / 3, 0, 0], atol=1e-12)
    depth = np.full((48, 64), 2.0, np.float32)
    motion_px = camera.fx * 0.03 / 2.0  # over the whole exposure of one frame interval
    assert motion_px == pytest.approx(0.787, abs=1e-3)
    assert subpose_count(path, camera, depth, 0.1, 99) == 9  # ceil(7.87) = 8 -> odd
    assert subpose_count(path, camera, depth, 0.1, 6) == 5
    assert subpose_count(path, camera, depth, 1.0, 99) == 1  # under a pixel: one sharp render
    assert subpose_count(None, camera, depth, 0.1, 99) == 1
    assert exposure_path(frame, 10.0, [(10.0 - 1 / 30, frame)], 0.0) is None


def fit(camera, views, schedule, blurred):
    """A map densified from the views' depth and fitted to their (blurred) colours; ``blurred``: through their
    exposure poses."""
    gaussian_map = GaussianMap(MapperConfig())
    for anchor_id, (poses, images) in enumerate(views):
        gaussian_map.set_anchor_pose(anchor_id, poses[len(poses) // 2])
        rendered = gaussian_map.render(camera, poses[len(poses) // 2]) if len(gaussian_map) else None
        gaussian_map.densify(anchor_id, camera, images, rendered)
    gaussian_map.optimise(camera, [(poses if blurred else poses[len(poses) // 2], images) for poses, images in views],
                          schedule)
    return gaussian_map


def test_a_map_fitted_through_the_exposure_poses_is_sharper_than_one_fitted_to_the_blur():
    """Two views of the synthetic room, each blurred by a fast pan (about 7 px of motion over the exposure at
    64x48); the map that renders them as the mean over their exposure path comes out closer to the sharp frames."""
    scene, camera = make_room_scene(0), default_camera(64, 48)
    exposure_s, speed = 1 / 30, np.array([0.0, 0.0, 0.0, 0.0, 4.0, 0.0])  # 4 rad/s about the camera's y axis
    views, sharp = [], []
    for eye in ([0.3, 0.2, 1.2], [-0.2, 0.3, 1.2]):
        pose = look_at(np.array(eye), np.array([2.0, 1.0, 1.0]))
        true_path = lambda t: pose @ exp_se3(t * speed)  # noqa: E731
        rgb, depth = render(scene, camera, pose)
        blurred = np.mean([render(scene, camera, true_path(t))[0]
                           for t in (np.arange(15) + 0.5) / 15 * exposure_s - exposure_s / 2], axis=0)
        path = exposure_path(pose, 0.0, [(-1 / 30, true_path(-1 / 30)), (1 / 30, true_path(1 / 30))], exposure_s)
        count = subpose_count(path, camera, depth, 1.0, 9)
        assert count == 9  # capped: about 7 px of motion start to end, and more at the image's sides
        views.append((pose @ path.poses(count), ViewImages(torch.from_numpy(blurred), torch.from_numpy(depth))))
        sharp.append(rgb)
    scores = {}
    for blurred in (False, True):
        gaussian_map = fit(camera, views, [0, 1] * 30, blurred)
        scores[blurred] = np.mean([psnr_db(gaussian_map.render(camera, poses[len(poses) // 2]).rgb.clamp(0, 1).numpy(),
                                           target) for (poses, _), target in zip(views, sharp)])
        if blurred:
            # Rendered through its exposure poses, the blur-aware map reproduces the blurred input too.
            again = render_exposure(gaussian_map.gaussians(), camera, views[0][0]).rgb.detach().clamp(0, 1).numpy()
            assert psnr_db(again, views[0][1].rgb.numpy()) > scores[blurred]
    assert scores[True] > scores[False] + 1.0, scores


def test_the_exposure_comes_from_the_key_else_the_synthetic_camera_file_else_it_is_off(tmp_path):
    write_synthetic_sequence(tmp_path / "blurred", SynthOptions(frame_count=2, width=32, height=24, exposure_s=0.02))
    write_synthetic_sequence(tmp_path / "sharp", SynthOptions(frame_count=2, width=32, height=24))
    blurred, sharp = open_sequence(tmp_path / "blurred"), open_sequence(tmp_path / "sharp")
    assert blurred.sensor.exposure_s == 0.02 and sharp.sensor.exposure_s is None
    assert blur_exposure_s(BridgeConfig(), blurred) == 0.02
    assert blur_exposure_s(BridgeConfig(), sharp) == 0.0
    assert blur_exposure_s(BridgeConfig(blur_exposure_s=0.01), sharp) == 0.01
    assert blur_exposure_s(BridgeConfig(blur_exposure_s=0.0), blurred) == 0.0
    assert blur_exposure_s(BridgeConfig(enabled=False), blurred) == 0.0
    with pytest.raises(ConfigError, match="bridge.blur_exposure_s"):
        load_config(None, ["bridge.blur_exposure_s=-0.01"])


def test_round_robin_gives_each_view_its_steps_in_rounds():
    assert round_robin([2, 4, 1]) == [0, 1, 2, 0, 1, 1, 1]
    assert round_robin([3, 3]) == [0, 1] * 3
    assert round_robin([0, 2]) == [1, 1] and round_robin([]) == []


def test_a_view_rendered_over_its_exposure_gets_blur_steps_factor_times_the_steps(synthetic_sequence_dir, tmp_path):
    """With blur modelling on, each view rendered over more than one sub-pose gets ``blur_steps_factor`` times the
    online and final Adam steps; a view rendered sharp as many as before (the first, mapped before any tracked
    neighbour gave it an exposure path)."""
    sequence = open_sequence(synthetic_sequence_dir, max_frames=13)
    mapper = dataclasses.replace(MapperConfig(), resolution_scale=0.25, iterations=4, final_iterations_per_view=2,
                                 sharp_iterations_per_view=0)
    # Every tracked motion is "blur" at a hundredth of a pixel: each view with a path gets 3 sub-poses.
    bridge = BridgeConfig(blur_exposure_s=1 / 30, blur_step_px=0.01, blur_max_subposes=3, blur_steps_factor=3)
    run_log = RunLog(tmp_path / "run.log")
    stage = MappingStage(sequence, mapper, bridge, run_log)
    schedules = []
    optimise = stage.map.optimise

    def recording(camera, views, schedule, exposures=None):
        schedules.append((len(views), list(schedule)))
        return optimise(camera, views, schedule, exposures)

    stage.map.optimise = recording
    frontend = GroundTruthFrontend(sequence.ground_truth, every=6)
    for index in range(len(sequence)):
        pose = sequence.ground_truth.world_from_camera[index]
        is_keyframe = index % 6 == 0
        stage.on_tracked(TrackResult(index, float(sequence.timestamps_s[index]), pose, True, is_keyframe, 100),
                         sequence[index])
        if is_keyframe:
            stage.on_keyframe(frontend.event(index), sequence[index], dict(frontend.poses))
    online = [len(schedule) for _, schedule in schedules]
    stage.finish(dict(frontend.poses))
    run_log.close()
    assert [view.frame_index for view in stage.views] == [0, 6, 12]
    assert online == [4, 12, 12]
    # By the final pass frame 1's track gave the first view its path too: 2 x 3 steps for every view.
    assert [stage.subposes[view.frame_index] for view in stage.views] == [3, 3, 3]
    (count, final), = schedules[len(online):]
    assert count == 3 and [final.count(row) for row in range(3)] == [6, 6, 6]
