"""Fusion Bridge: view selection on hand-made counts, gates on a hand-made render, pose refinement on a synthetic scene."""

import dataclasses

import numpy as np
import pytest
import torch

from tambridge.bridge.refinement import pixel_gates, refine_render_pose, reprojection_error_px
from tambridge.bridge.view_selection import (SHARPER_FRAME, Candidate, Selection, covisibility_selection, select_view,
                                             sharpest_candidate, too_blurred)
from tambridge.bridge.config import BridgeConfig
from tambridge.gaussians.config import MapperConfig
from tambridge.frontend.contract import KeyframeEvent
from tambridge.gaussians.mapper import GaussianMap, ViewImages
from tambridge.threads import TORCH_THREADS, compute_threads
from tambridge.geometry import exp_se3, inverse, log_se3, transform_points
from tambridge.io.synthetic import default_camera, loop_path, make_room_scene, render
from tambridge.io.tum import Frame, open_sequence
from tambridge.frontend.contract import TrackResult
from tambridge.images import sharpness
from tambridge.mapping.stage import MappingStage
from tambridge.evaluation.mapping import score_views
from tambridge.runlog import RunLog


@pytest.fixture(autouse=True)
def one_thread_each():
    """As the pipeline maps (see TORCH_THREADS): torch's and numba's OpenMP pools otherwise fight for 2 cores."""
    with compute_threads(TORCH_THREADS, 1):
        yield


@pytest.mark.parametrize(
    "shared, total, expected",
    [
        (20, 100, Selection.SELECTED),  # beta <= M: the lower bound is inclusive
        (19, 100, Selection.TOO_FEW_SHARED),
        (74, 100, Selection.SELECTED),  # 74 < 0.75 * 100
        (75, 100, Selection.TOO_SIMILAR),  # the upper bound is exclusive
        (30, 30, Selection.TOO_SIMILAR),
        (25, 26, Selection.TOO_SIMILAR),  # 25 >= 19.5
        (0, 0, Selection.NO_SPARSE_MAP),  # Open3D frontends: every keyframe is a view
        (10, 20, Selection.TOO_FEW_SHARED),  # M < beta wins even when M < alpha T
    ],
)
def test_view_selection_follows_eq_3(shared, total, expected):
    selection = covisibility_selection(shared, total, alpha=0.75, beta=20)
    assert selection == expected
    assert selection.selected == (expected in (Selection.SELECTED, Selection.NO_SPARSE_MAP))


def test_first_keyframe_is_always_a_view_and_bridge_off_takes_every_keyframe():
    event = KeyframeEvent(3, 30, 1.0, np.eye(4), np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0, np.int64), 95, 100)
    assert select_view(event, is_first=True, enabled=True, alpha=0.75, beta=20) == Selection.FIRST
    assert select_view(event, is_first=False, enabled=True, alpha=0.75, beta=20) == Selection.TOO_SIMILAR
    assert select_view(event, is_first=False, enabled=False, alpha=0.75, beta=20) == Selection.BRIDGE_OFF
    assert Selection.BRIDGE_OFF.selected and Selection.FIRST.selected


def test_gates_on_a_hand_made_render():
    observed = torch.tensor([[2.0, 2.0, 0.0, 2.0], [2.0, 2.0, 2.0, 2.0]])
    # Unnormalised rendered depth = silhouette * surface depth.
    silhouette = torch.tensor([[1.0, 0.995, 1.0, 0.98], [1.0, 1.0, 1.0, 0.0]])
    surface = torch.tensor([[2.01, 1.99, 2.0, 2.0], [2.02, 2.0, 3.5, 2.0]])
    rendered = silhouette * surface
    gates = pixel_gates(observed, rendered, silhouette, gamma=0.99, depth_outlier_factor=10.0)
    expected = torch.tensor([
        [True, True, False, False],  # no sensor depth at (0, 2); border mask 0.98 <= gamma at (0, 3)
        [True, True, False, False],  # 1.5 m residual at (1, 2) is > 10 x the median (0.01 m); nothing rendered at (1, 3)
    ])
    assert torch.equal(gates, expected)


def test_reprojection_error_is_the_mean_pixel_distance():
    camera = default_camera(160, 120)
    world_from_camera = np.eye(4)
    points = np.array([[0.0, 0.0, 2.0], [0.5, -0.25, 2.5]])
    keypoints = np.array([[camera.cx + 3.0, camera.cy + 4.0], [camera.fx * 0.2 + camera.cx, camera.fy * -0.1 + camera.cy]])
    error = reprojection_error_px(camera, torch.from_numpy(world_from_camera), None, torch.from_numpy(points), torch.from_numpy(keypoints))
    assert float(error) == pytest.approx((5.0 + 0.0) / 2)


def random_perturbation(rng, translation_m, rotation_deg):
    direction = rng.normal(size=6)
    rho = direction[:3] / np.linalg.norm(direction[:3]) * translation_m
    phi = direction[3:] / np.linalg.norm(direction[3:]) * np.deg2rad(rotation_deg)
    return exp_se3(np.concatenate([rho, phi]))


def pose_error(a_from_b, reference):
    error = log_se3(inverse(reference) @ a_from_b)
    return np.linalg.norm(error[:3]), np.rad2deg(np.linalg.norm(error[3:]))


@pytest.fixture(scope="module")
def synthetic_views():
    """Frames 0, 1 and 2 of a 60-frame loop in the synthetic room: ``(camera, ground-truth poses, {index: images})``."""
    scene, camera, poses = make_room_scene(0), default_camera(160, 120), loop_path(60)
    views = {}
    for index in (0, 1, 2):
        colour, depth = render(scene, camera, poses[index])
        views[index] = ViewImages(torch.from_numpy(colour), torch.from_numpy(depth))
    return camera, poses, views


@pytest.fixture(scope="module")
def synthetic_map(synthetic_views):
    """A map of frames 0 and 2 at ground-truth poses (a few Adam steps), and frame 1 to refine."""
    camera, poses, views = synthetic_views
    torch.manual_seed(0)
    gaussian_map = GaussianMap(MapperConfig())
    with compute_threads(TORCH_THREADS, 1):  # module scope: set up before the autouse fixture
        for index in (0, 2):
            gaussian_map.set_anchor_pose(index, poses[index])
            rendered = gaussian_map.render(camera, poses[index]) if len(gaussian_map) else None
            gaussian_map.densify(index, camera, views[index], rendered)
        gaussian_map.optimise(camera, [(poses[0], views[0]), (poses[2], views[2])], [0, 1] * 10)
    return gaussian_map, camera, poses, views


@pytest.mark.slow
def test_refinement_recovers_a_pose_perturbation(synthetic_map):
    gaussian_map, camera, poses, views = synthetic_map
    start = poses[1] @ random_perturbation(np.random.default_rng(0), 0.02, 1.0)
    config = dataclasses.replace(BridgeConfig(), iterations=20)
    result = refine_render_pose(gaussian_map.gaussians(), camera, start, views[1].rgb, views[1].depth_m,
                         np.zeros((0, 3)), np.zeros((0, 2)), config)
    translation_m, rotation_deg = pose_error(result.world_from_camera, poses[1])
    # A third of the start's translation error and a fifth of its rotation error: this small map bounds how far
    # below that the refinement gets (more iterations do not help).
    assert translation_m < 0.02 / 3 and rotation_deg < 1.0 / 5
    assert result.loss_final < 0.5 * result.loss_initial and result.gated_fraction > 0.5


def test_reprojection_term_alone_pulls_the_pose_back(synthetic_views):
    """With no map under the view (all pixels gated out) the matched points alone drive the refinement."""
    camera, poses, views = synthetic_views
    rng = np.random.default_rng(1)
    points_camera = np.column_stack([rng.uniform(-1, 1, 60), rng.uniform(-0.7, 0.7, 60), rng.uniform(1.5, 3.0, 60)])
    keypoints = points_camera[:, :2] / points_camera[:, 2:] * [camera.fx, camera.fy] + [camera.cx, camera.cy]
    points_world = transform_points(poses[1], points_camera)
    start = poses[1] @ random_perturbation(rng, 0.02, 1.0)
    empty_map = GaussianMap(MapperConfig())
    config = dataclasses.replace(BridgeConfig(), iterations=60, w_colour=0.0, w_depth=0.0)
    result = refine_render_pose(empty_map.gaussians(), camera, start, views[1].rgb, views[1].depth_m, points_world, keypoints, config)
    translation_m, rotation_deg = pose_error(result.world_from_camera, poses[1])
    assert translation_m < 0.02 / 3 and rotation_deg < 1.0 / 3
    assert not result.skipped and result.gated_fraction == 0.0


def test_refinement_is_skipped_without_map_or_points(synthetic_views):
    camera, poses, views = synthetic_views
    result = refine_render_pose(GaussianMap(MapperConfig()).gaussians(), camera, poses[1], views[1].rgb, views[1].depth_m,
                         np.zeros((0, 3)), np.zeros((0, 2)), BridgeConfig())
    assert result.skipped
    np.testing.assert_array_equal(result.world_from_camera, poses[1])


def candidate(index, sharpness_score, tracked_points):
    return Candidate(index, np.eye(4), sharpness_score, tracked_points)


def test_sharpest_candidate_within_eq_3_bounds_is_chosen():
    keyframe = candidate(10, 50.0, 60)  # T = 100 below: M = 60 passes eq. 3
    window = [candidate(5, 400.0, 90),  # the sharpest, but 90 >= 0.75 T: too similar to the previous keyframe
              candidate(6, 200.0, 70),  # sharpest within the bounds
              candidate(7, 150.0, 10),  # under beta
              candidate(8, 120.0, 50)]
    assert sharpest_candidate(keyframe, window, 100, 0.75, 20).frame_index == 6
    assert sharpest_candidate(keyframe, window[:1] + window[2:3], 100, 0.75, 20).frame_index == 10
    # Without a sparse map (T = 0) every tracked candidate passes; a tie keeps the keyframe.
    assert sharpest_candidate(keyframe, window, 0, 0.75, 20).frame_index == 5
    assert sharpest_candidate(keyframe, [candidate(9, 50.0, 60)], 100, 0.75, 20).frame_index == 10
    # A margin keeps the keyframe against a candidate only a little sharper.
    assert sharpest_candidate(keyframe, [candidate(9, 55.0, 60)], 100, 0.75, 20, margin=1.2).frame_index == 10
    assert sharpest_candidate(keyframe, [candidate(9, 65.0, 60)], 100, 0.75, 20, margin=1.2).frame_index == 9


def test_a_blurred_outlier_is_too_blurred_and_a_typical_frame_is_not():
    recent = [100.0, 120.0, 90.0, 110.0, 105.0]
    assert too_blurred(20.0, recent, 0.35, 3)
    assert not too_blurred(80.0, recent, 0.35, 3)
    assert not too_blurred(20.0, recent, 0.0, 3)  # ratio 0: never
    assert not too_blurred(20.0, recent[:2], 0.35, 3)  # too few frames for a median


def test_refinement_is_skipped_at_the_reprojection_noise_floor(synthetic_views):
    """Points that reproject within the floor at the start pose keep it without a render; above it they do not."""
    camera, poses, views = synthetic_views
    rng = np.random.default_rng(2)
    points_camera = np.column_stack([rng.uniform(-1, 1, 40), rng.uniform(-0.7, 0.7, 40), rng.uniform(1.5, 3.0, 40)])
    keypoints = points_camera[:, :2] / points_camera[:, 2:] * [camera.fx, camera.fy] + [camera.cx, camera.cy]
    keypoints = keypoints + rng.normal(0.0, 0.3, keypoints.shape)  # keypoint noise of 0.3 px
    points_world = transform_points(poses[1], points_camera)
    empty_map = GaussianMap(MapperConfig())
    floor = dataclasses.replace(BridgeConfig(), reprojection_floor_px=1.0, iterations=5)
    kept = refine_render_pose(empty_map.gaussians(), camera, poses[1], views[1].rgb, views[1].depth_m, points_world,
                              keypoints, floor)
    assert kept.skipped and 0.1 < kept.reprojection_px < 1.0
    np.testing.assert_array_equal(kept.world_from_camera, poses[1])
    start = poses[1] @ random_perturbation(rng, 0.02, 1.0)  # several pixels off: refined
    moved = refine_render_pose(empty_map.gaussians(), camera, start, views[1].rgb, views[1].depth_m, points_world,
                               keypoints, floor)
    assert not moved.skipped and moved.reprojection_px > 1.0 and moved.loss_final < moved.loss_initial


def test_colour_term_scales_with_the_colour_weight(synthetic_map):
    """The joint loss at the start pose is linear in the colour weight (0 drops the colour term)."""
    gaussian_map, camera, poses, views = synthetic_map
    config = dataclasses.replace(BridgeConfig(), iterations=1)
    start = poses[1] @ random_perturbation(np.random.default_rng(3), 0.01, 0.5)
    losses = [refine_render_pose(gaussian_map.gaussians(), camera, start, views[1].rgb, views[1].depth_m, np.zeros((0, 3)),
                                 np.zeros((0, 2)), config, colour_weight=weight).loss_initial for weight in (0.0, 0.5, 1.0)]
    assert losses[2] - losses[0] > 1e-3
    assert np.isclose(losses[2] - losses[0], 2 * (losses[1] - losses[0]), rtol=1e-4)


def blurred(rgb, sigma=3.0):
    import cv2
    return cv2.GaussianBlur(rgb, (0, 0), sigma)


def map_with_blurred_keyframes(sequence, tmp_path, bridge, keyframes, blurred_frames):
    """Map ``keyframes`` (frame indices) of ``sequence`` at ground-truth poses, every frame tracked with the blurred
    colour where its index is in ``blurred_frames`` (only the frames given to the stage are blurred: the files, read
    back for a replacing frame and for scoring, stay sharp)."""
    poses = sequence.ground_truth.world_from_camera
    mapper = MapperConfig(resolution_scale=0.5, iterations=10, coverage_unexplained=0.0)
    run_log = RunLog(tmp_path / "run.log")
    try:
        stage = MappingStage(sequence, mapper, bridge, run_log, seed=0)
        keyframe_poses = {}
        for index in range(keyframes[-1] + 1):
            frame = sequence[index]
            if index in blurred_frames:
                frame = Frame(frame.index, frame.timestamp_s, blurred(frame.rgb), frame.depth_m)
            stage.on_tracked(TrackResult(index, 0.0, poses[index], True, index in keyframes, 60), frame)
            if index in keyframes:
                keyframe_id = len(keyframe_poses)
                keyframe_poses[keyframe_id] = poses[index]
                event = KeyframeEvent(keyframe_id, index, 0.0, poses[index], np.zeros((0, 3)), np.zeros((0, 2)),
                                      np.zeros(0, np.int64), shared_with_previous=60, previous_total=100)
                stage.on_keyframe(event, frame, dict(keyframe_poses))
        return stage
    finally:
        run_log.close()


def test_blur_aware_selection_maps_the_sharp_frame_before_a_blurred_keyframe(synthetic_sequence_dir, tmp_path):
    """Keyframe at frame 6 blurred, frame 5 sharp: the view is frame 5 at its tracked pose, and frames rendered
    after it follow the frontend's relative motion."""
    sequence = open_sequence(synthetic_sequence_dir, max_frames=8)
    poses = sequence.ground_truth.world_from_camera
    stage = map_with_blurred_keyframes(sequence, tmp_path, BridgeConfig(sharpest_window=2), [0, 6], {4, 6})
    assert [view.frame_index for view in stage.views] == [0, 5]
    assert stage.selections[SHARPER_FRAME] == 1 and stage.selections[Selection.SELECTED.name] == 1
    np.testing.assert_allclose(stage.views[1].keyframe_from_view, inverse(poses[6]) @ poses[5], atol=1e-12)
    np.testing.assert_allclose(stage.view_pose(stage.views[1]), poses[5], atol=1e-12)
    np.testing.assert_allclose(stage.rendering_pose(7, poses[7]), poses[7], atol=1e-12)


def test_a_view_far_blurrier_than_the_recent_frames_is_skipped(synthetic_sequence_dir, tmp_path):
    sequence = open_sequence(synthetic_sequence_dir, max_frames=8)
    stage = map_with_blurred_keyframes(sequence, tmp_path, BridgeConfig(sharpest_window=0), [0, 6], {6})
    assert [view.frame_index for view in stage.views] == [0]
    assert stage.selections[Selection.TOO_BLURRED.name] == 1
    assert sharpness(blurred(sequence[6].rgb)) < 0.35 * sharpness(sequence[6].rgb)


@pytest.mark.slow
def test_blur_aware_selection_beats_keyframe_only_selection_against_the_sharp_frames(synthetic_sequence_dir, tmp_path):
    """Every third frame a keyframe and blurred (the frame before it sharp): scored against the sharp files, the map
    of the sharper frames renders the frames between better than the map of the blurred keyframes."""
    sequence = open_sequence(synthetic_sequence_dir, max_frames=16)
    poses = sequence.ground_truth.world_from_camera
    keyframes = [0, 3, 6, 9, 12, 15]
    blurred_frames = set(keyframes[1:])
    psnr_db = {}
    for name, bridge in {"keyframes": BridgeConfig(sharpest_window=0, blur_reject_ratio=0.0),
                         "sharpest": BridgeConfig()}.items():
        stage = map_with_blurred_keyframes(sequence, tmp_path, bridge, keyframes, blurred_frames)
        stage.finish({i: poses[k] for i, k in enumerate(keyframes)})
        psnr_db[name] = float(np.mean(score_views(stage, stage.rendering_poses(sequence.ground_truth), [1, 4, 7, 10, 13]).psnr_db))
    # The bound lies 1 dB inside this run's gain (mapping is deterministic).
    assert psnr_db["sharpest"] > psnr_db["keyframes"] + 1.8, psnr_db


def test_each_view_gets_its_exposure_path_from_the_tracked_neighbours_and_keeps_it_refined(synthetic_sequence_dir,
                                                                                            tmp_path):
    """Views at frames 0 and 4: mapped with the previous frame only (frame 0: none), then through both neighbours
    once the next frame is tracked; the path's samples are the neighbours' poses relative to the view's frame."""
    sequence = open_sequence(synthetic_sequence_dir, max_frames=6)
    poses, times = sequence.ground_truth.world_from_camera, sequence.timestamps_s
    bridge = BridgeConfig(sharpest_window=0, blur_exposure_s=0.03)
    stage = map_with_blurred_keyframes(sequence, tmp_path, bridge, [0, 4], set())
    first, last = stage.views
    np.testing.assert_allclose(first.exposure_path.times_s, [0.0, times[1] - times[0]])
    np.testing.assert_allclose(last.exposure_path.times_s, [times[3] - times[4], 0.0])
    np.testing.assert_allclose(last.exposure_path.frame_from_tracked[0], inverse(poses[4]) @ poses[3], atol=1e-12)
    stage.on_tracked(TrackResult(5, 0.0, poses[5], True, False, 60), sequence[5])
    np.testing.assert_allclose(last.exposure_path.times_s, [times[3] - times[4], 0.0, times[5] - times[4]])
    np.testing.assert_allclose(last.exposure_path.frame_from_tracked[2], inverse(poses[4]) @ poses[5], atol=1e-12)
    assert last.exposure_path.exposure_s == 0.03
    off = map_with_blurred_keyframes(sequence, tmp_path / "off", BridgeConfig(sharpest_window=0), [0, 4], set())
    assert all(view.exposure_path is None for view in off.views)  # the synthetic fixture has no exposure_s
