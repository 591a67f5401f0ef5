"""The sharpening pass after tracking (MappingStage.sharpen, GaussianMap.densify_colour_error): detail at the
resolution a user views the map, built from frames read again a chunk at a time."""

import copy
import dataclasses
import logging
import types

import numpy as np
import pytest
import torch

from tambridge.bridge.blur import exposure_path
from tambridge.bridge.config import BridgeConfig
from tambridge.gaussians.config import MapperConfig
from tambridge.gaussians.mapper import GaussianMap, ViewExposure, ViewImages
from tambridge.io.synthetic import default_camera
from tambridge.io.tum import open_sequence
from tambridge.mapping.stage import FrameBetween, MappingStage, frames_between_views, resize_frame, resized_frame
from tambridge.runlog import RunLog
from tambridge.threads import TORCH_THREADS, compute_threads
from tests.test_exported import gained_sequence
from tests.test_mapper import GroundTruthFrontend


@pytest.fixture(autouse=True)
def one_thread_each():
    with compute_threads(TORCH_THREADS, 1):
        yield


def full_resolution_l1(stage: MappingStage, through_exposures: bool = True) -> float:
    """Mean colour L1 of the mapping views rendered at the camera's resolution, through their exposures or (false)
    as exported, the map's own colours."""
    errors = []
    for view in stage.views:
        frame = resize_frame(stage.sequence[view.frame_index], 1.0)
        rendered = stage.map.render(stage.sequence.camera, stage.view_pose(view)).rgb
        with torch.no_grad():
            rendered = (view.exposure.apply(rendered) if through_exposures else rendered).clamp(0.0, 1.0)
        errors.append(float((rendered - frame.rgb).abs().mean()))
    return float(np.mean(errors))


def coarse_stage(sequence, tmp_path, **mapper):
    """A map of every 6th frame at ground-truth poses, mapped at a quarter of the synthetic 160x120 frames."""
    config = dataclasses.replace(MapperConfig(), **{"resolution_scale": 0.25, "iterations": 10,
                                                    "sharp_iterations_per_view": 0, **mapper})
    run_log = RunLog(tmp_path / "run.log")
    stage = MappingStage(sequence, config, BridgeConfig(enabled=False), run_log)
    frontend = GroundTruthFrontend(sequence.ground_truth, every=6)
    for index in range(0, len(sequence), 6):
        stage.on_keyframe(frontend.event(index), sequence[index], dict(frontend.poses))
    stage.finish(dict(frontend.poses))
    run_log.close()
    return stage, dict(frontend.poses)


@pytest.mark.slow
def test_sharpening_lowers_the_full_resolution_error_of_a_coarse_map(synthetic_sequence_dir, tmp_path):
    sequence = open_sequence(synthetic_sequence_dir, max_frames=24)
    stage, _ = coarse_stage(sequence, tmp_path)
    before, count_before = full_resolution_l1(stage), len(stage.map)
    state = copy.deepcopy(stage.state_dict())
    after = {}
    for densify_error in (0.0, 0.1):
        stage.load_state_dict(copy.deepcopy(state))
        stage.mapper_config = dataclasses.replace(stage.mapper_config, sharp_iterations_per_view=6, sharp_resolution_scale=1.0,
                                                  sharp_densify_error=densify_error, sharp_densify_fraction=0.02)
        stage.sharpen()
        after[densify_error] = full_resolution_l1(stage), len(stage.map)
    assert after[0.0][1] == count_before
    assert count_before < after[0.1][1] <= count_before + 4 * int(0.02 * 160 * 120)  # the worst 2 % of each view
    assert after[0.0][0] < 0.95 * before and after[0.1][0] < 0.95 * before, (before, after)


def test_sharpening_reads_frames_again_at_its_resolution_a_chunk_at_a_time(synthetic_sequence_dir, tmp_path, monkeypatch):
    sequence = open_sequence(synthetic_sequence_dir, max_frames=24)
    stage, _ = coarse_stage(sequence, tmp_path, window_size=3, iterations=2)
    cache = dict(stage._cache)
    stage.mapper_config = dataclasses.replace(stage.mapper_config, sharp_iterations_per_view=2, sharp_resolution_scale=1.5,
                                              sharp_lr_scale_start=2.0, sharp_lr_scale_end=0.4)
    calls, scales = [], []
    optimise = stage.map.optimise

    def recording(camera, views, schedule, exposures=None, learning_rate_scale=1.0,
                  w_colour_squared=0.0):
        calls.append(((camera.width, camera.height), [tuple(images.rgb.shape) for _, images in views], list(schedule)))
        scales.append(learning_rate_scale)
        return optimise(camera, views, schedule, exposures, learning_rate_scale, w_colour_squared)

    monkeypatch.setattr(stage.map, "optimise", recording)
    stage.sharpen()
    # 4 views in chunks of the window size (3), at 1.5 x 160x120, two rounds of one step per view; the mapping cache
    # is untouched.
    assert [len(shapes) for _, shapes, _ in calls] == [3, 1, 3, 1]
    assert all(size == (240, 180) for size, _, _ in calls)
    assert all(shape == (180, 240, 3) for _, shapes, _ in calls for shape in shapes)
    assert [schedule for _, _, schedule in calls] == [[0, 1, 2], [0], [0, 1, 2], [0]]
    assert stage._cache.keys() == cache.keys()
    assert all(images.rgb.shape == (30, 40, 3) for images in stage._cache.values())
    # The learning rates fall linearly over the pass's four chunks, from 2 towards 0.4 times the online ones.
    np.testing.assert_allclose(scales, [2.0, 1.6, 1.2, 0.8])


def test_sharpening_keeps_its_first_rounds_frames_within_budget_and_fits_the_same_map(synthetic_sequence_dir, tmp_path,
                                                                                      monkeypatch, caplog):
    """Frames kept from the first round spare the later rounds' reads (decoding, registration, the rolling shutter's
    resampling) and are exactly the frames read again: the map after the pass is the same to the bit."""
    sequence = open_sequence(synthetic_sequence_dir, max_frames=24)
    stage, _ = coarse_stage(sequence, tmp_path, window_size=3, iterations=2)
    before = copy.deepcopy(stage.state_dict())
    frame_bytes = resized_frame(sequence[0], 1.5).nbytes  # 240x180: colour uint8 and depth float32
    assert frame_bytes == 240 * 180 * (3 + 4)
    reads, maps = {}, {}
    for kept_frames in (0, 2.5, 4):
        stage.load_state_dict(copy.deepcopy(before))
        stage.mapper_config = dataclasses.replace(stage.mapper_config, sharp_iterations_per_view=3,
                                                  sharp_resolution_scale=1.5,
                                                  sharp_frames_kept_mb=kept_frames * frame_bytes / 2**20)
        at_frame_time = MappingStage.at_frame_time
        read = []
        monkeypatch.setattr(stage, "at_frame_time", lambda frame: read.append(frame.index) or at_frame_time(stage, frame))
        stage.sharpen()
        reads[kept_frames] = read
        maps[kept_frames] = stage.map.gaussians()
    # 4 views, three rounds: every view read each round; two kept (room for 2.5), read once; all four read once.
    assert [len(reads[kept]) for kept in (0, 2.5, 4)] == [12, 8, 4]
    assert sorted(set(reads[4])) == sorted(view.frame_index for view in stage.views)
    for kept in (2.5, 4):
        for name in ("means_m", "rgb", "log_radii_m", "opacity_logits"):
            assert torch.equal(getattr(maps[kept], name), getattr(maps[0], name)), (kept, name)
    # A pass of one round has no later round to keep frames for.
    stage.mapper_config = dataclasses.replace(stage.mapper_config, sharp_iterations_per_view=1)
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="tambridge.mapping"):
        stage.sharpen()
    assert caplog.messages[-1].endswith("; 0 frames kept for the later rounds (0 MB)"), caplog.messages


def test_sharpening_never_runs_coarser_than_the_mapping(synthetic_sequence_dir, tmp_path, monkeypatch):
    sequence = open_sequence(synthetic_sequence_dir, max_frames=24)
    stage, _ = coarse_stage(sequence, tmp_path, resolution_scale=0.5, window_size=3, iterations=2)
    stage.mapper_config = dataclasses.replace(stage.mapper_config, sharp_iterations_per_view=1, sharp_resolution_scale=0.25)
    sizes = []
    optimise = stage.map.optimise

    def recording(camera, views, schedule, exposures=None, learning_rate_scale=1.0,
                  w_colour_squared=0.0):
        sizes.append((camera.width, camera.height))
        return optimise(camera, views, schedule, exposures, learning_rate_scale, w_colour_squared)

    monkeypatch.setattr(stage.map, "optimise", recording)
    stage.sharpen()
    # Mapped at half of 160x120: a pass asked for a quarter runs at the mapping's 80x60.
    assert sizes and set(sizes) == {(80, 60)}


def test_frames_between_are_fitted_at_their_own_resolution_in_chunks_of_their_own(synthetic_sequence_dir, tmp_path,
                                                                                   monkeypatch):
    sequence = open_sequence(synthetic_sequence_dir, max_frames=24)
    stage, _ = coarse_stage(sequence, tmp_path, window_size=3, iterations=2)
    stage.mapper_config = dataclasses.replace(stage.mapper_config, sharp_iterations_per_view=2, sharp_resolution_scale=1.5,
                                              sharp_frames_between=1, sharp_between_resolution_scale=0.5)
    tracking = types.SimpleNamespace(trajectory=sequence.ground_truth, tracked=np.ones(len(sequence), bool),
                                     tracked_by_depth=None)
    frames = stage.frames_between(tracking, held_out=range(0, len(sequence), 3))
    assert [frame.frame_index for frame in frames] == [4, 10, 16, 22]
    calls = []
    optimise = stage.map.optimise

    def recording(camera, views, schedule, exposures=None, learning_rate_scale=1.0,
                  w_colour_squared=0.0):
        calls.append(((camera.width, camera.height), {tuple(images.rgb.shape) for _, images in views}, len(views)))
        return optimise(camera, views, schedule, exposures, learning_rate_scale, w_colour_squared)

    monkeypatch.setattr(stage.map, "optimise", recording)
    stage.sharpen(frames)
    # Per round: the 4 views in chunks of 3 and 1 at 240x180, the 4 frames between in chunks of 3 and 1 at 80x60.
    assert sorted((size, count) for size, _, count in calls) == sorted([((240, 180), 3), ((240, 180), 1),
                                                                        ((80, 60), 3), ((80, 60), 1)] * 2)
    assert all(shapes == {(size[1], size[0], 3)} for size, shapes, _ in calls)

def test_frames_tracked_by_their_depth_alone_are_never_fitted_between_the_views(synthetic_sequence_dir, tmp_path):
    """Their colour is what the tracker could not use (a covered lens): the middles are taken among the others."""
    sequence = open_sequence(synthetic_sequence_dir, max_frames=24)
    stage, _ = coarse_stage(sequence, tmp_path, sharp_frames_between=1)
    by_depth = np.zeros(len(sequence), bool)
    by_depth[[4, 10]] = True
    tracking = types.SimpleNamespace(trajectory=sequence.ground_truth, tracked=np.ones(len(sequence), bool),
                                     tracked_by_depth=by_depth)
    # Views at 0, 6, 12 and 18, every 3rd frame held out: without the mark [4, 10, 16, 22] (the test below).
    assert [frame.frame_index for frame in stage.frames_between(tracking, range(0, len(sequence), 3))] == [2, 8, 16, 22]


def test_with_the_bridge_on_the_frames_between_are_the_sharpest_the_tracker_scored(synthetic_sequence_dir, tmp_path):
    sequence = open_sequence(synthetic_sequence_dir, max_frames=24)
    stage, _ = coarse_stage(sequence, tmp_path, sharp_frames_between=1)
    tracking = types.SimpleNamespace(trajectory=sequence.ground_truth, tracked=np.ones(len(sequence), bool),
                                     tracked_by_depth=None)
    held_out = range(0, len(sequence), 3)
    # Bridge off (the ablation): the middles of the usable frames between the views at 0, 6, 12 and 18.
    assert [frame.frame_index for frame in stage.frames_between(tracking, held_out)] == [4, 10, 16, 22]
    stage.bridge_config = BridgeConfig()
    # Scores as on_tracked records them; frame 9 is held out, so 8 is the sharpest usable frame of 7-11.
    stage.frame_sharpness = {index: 1.0 for index in range(len(sequence))} | {2: 5.0, 8: 3.0, 9: 9.0, 23: 2.0}
    frames = stage.frames_between(tracking, held_out)
    assert [frame.frame_index for frame in frames] == [2, 8, 13, 23]
    np.testing.assert_allclose(frames[1].world_from_camera, stage.rendering_pose(8, sequence.ground_truth.world_from_camera[8]))
    # With blur modelling on, a frame's path runs through its tracked neighbours (held out or not); the last frame
    # has only the one before it.
    stage.blur_exposure_s = 0.03
    frames = stage.frames_between(tracking, held_out)
    poses, times = sequence.ground_truth.world_from_camera, sequence.timestamps_s
    for frame, neighbours in zip(frames, ([1, 3], [7, 9], [12, 14], [22])):
        expected = exposure_path(poses[frame.frame_index], float(times[frame.frame_index]),
                                 [(float(times[other]), poses[other]) for other in neighbours], 0.03)
        np.testing.assert_allclose(frame.exposure_path.times_s, expected.times_s)
        np.testing.assert_allclose(frame.exposure_path.frame_from_tracked, expected.frame_from_tracked, atol=1e-12)


@pytest.mark.slow
def test_sharpening_against_the_frames_as_recorded_fits_what_a_viewer_shows(synthetic_sequence_dir, tmp_path):
    """Exposures that drifted to a 25 % gain (as auto exposure drives them on real data) leave the map's own colours
    dark: through them, the pass keeps the map dark; against the frames as recorded (sharp_through_exposures
    false) it brings the map's own colours, what splats.ply shows, to the frames, and leaves the exposures as they
    were."""
    sequence = open_sequence(synthetic_sequence_dir, max_frames=24)
    stage, _ = coarse_stage(sequence, tmp_path)
    with torch.no_grad():
        stage.map.recolour(ViewExposure(torch.tensor([[np.log(0.8)] * 3, [0.0] * 3], dtype=torch.float32)))
    drifted = torch.tensor([[np.log(1.25)] * 3, [0.0] * 3], dtype=torch.float32)
    state = copy.deepcopy(stage.state_dict())
    after = {}
    for through_exposures in (True, False):
        stage.load_state_dict(copy.deepcopy(state))
        for view in stage.views:
            view.exposure = ViewExposure(drifted, learning_rate=1e-2)
        before = full_resolution_l1(stage, through_exposures=False)
        stage.mapper_config = dataclasses.replace(stage.mapper_config, sharp_iterations_per_view=4,
                                                  sharp_through_exposures=through_exposures)
        stage.sharpen()
        after[through_exposures] = full_resolution_l1(stage, through_exposures=False)
        if not through_exposures:
            assert all(torch.equal(view.exposure.parameters.detach(), drifted) for view in stage.views)
    assert after[False] < 0.85 * before and after[False] < 0.85 * after[True], (before, after)


@pytest.mark.slow
def test_after_a_pass_as_recorded_the_views_exposures_follow_the_frames_gains(synthetic_sequence_dir, tmp_path):
    """The frames' gains run 1.16 (frame 0) to 0.86 (frame 12) and back, and the views' exposures have drifted to
    a 25 % gain. After the pass against the frames as recorded, ``finish`` refits each exposure to the map: every
    view's gain relative to the others is its frame's (within 4 %), and the views render through their exposures
    closer to their frames than through the stale ones; no exposure recolours the map; a view no exposure fits
    takes the identity."""
    gains = np.exp(0.15 * np.cos(2 * np.pi * np.arange(24) / 24))
    gained_sequence(synthetic_sequence_dir, tmp_path / "gained", gains)
    sequence = open_sequence(tmp_path / "gained", max_frames=24)
    stage, keyframe_poses = coarse_stage(sequence, tmp_path)
    drifted = torch.tensor([[np.log(1.25)] * 3, [0.0] * 3], dtype=torch.float32)
    for view in stage.views:
        view.exposure = ViewExposure(drifted, learning_rate=1e-2)
    stage.mapper_config = dataclasses.replace(stage.mapper_config, sharp_iterations_per_view=4)
    stage.sharpen()
    stale = full_resolution_l1(stage)
    stage.mapper_config = dataclasses.replace(stage.mapper_config, final_iterations_per_view=0)
    anchored = []
    stage.anchor_exposures = lambda: anchored.append(True)
    stage.finish(keyframe_poses)
    # The map keeps the frames' own colours: no view's exposure recolours it.
    assert not anchored
    fitted = np.array([np.exp(view.exposure.parameters.detach().numpy()[0]).mean() for view in stage.views])
    frames = [view.frame_index for view in stage.views]
    np.testing.assert_allclose(fitted / fitted.mean(), gains[frames] / np.mean(gains[frames]), rtol=0.04)
    assert full_resolution_l1(stage) < 0.8 * stale, (full_resolution_l1(stage), stale)
    # A view whose render covers nothing (its keyframe turned away from the map) renders in the map's own colours,
    # the frames' after this pass, not through its exposure from before it.
    last = stage.views[-1]
    last.exposure.reset(drifted)
    stage.keyframe_poses[last.keyframe_id] = stage.keyframe_poses[last.keyframe_id] @ np.diag([-1.0, 1.0, -1.0, 1.0])
    assert stage.refit_exposures() == len(stage.views) - 1
    assert torch.equal(last.exposure.parameters.detach(), torch.zeros((2, 3)))


def test_densify_colour_error_adds_one_pixel_gaussians_at_the_worst_pixels_within_budget():
    camera = default_camera(40, 30)
    gaussian_map = GaussianMap(MapperConfig())
    gaussian_map.set_anchor_pose(0, np.eye(4))
    # One grey Gaussian far off the frame's centre; the frame: black, with a bright 4x5 patch and a dim 3x3 one.
    gaussian_map.add(0, torch.tensor([[5.0, 5.0, 2.0]]), torch.full((1, 3), 0.5), torch.tensor([0.01]))
    rgb = torch.zeros((30, 40, 3))
    rgb[10:14, 10:15] = 1.0
    rgb[20:23, 30:33] = 0.3
    depth_m = torch.full((30, 40), 2.0)
    depth_m[10, 10] = 0.0  # no depth: never densified
    images = ViewImages(rgb, depth_m)
    assert gaussian_map.densify_colour_error(0, camera, images, None, threshold=0.2, fraction=1.0) == 19 + 9
    gaussian_map = GaussianMap(MapperConfig())
    gaussian_map.set_anchor_pose(0, np.eye(4))
    gaussian_map.add(0, torch.tensor([[5.0, 5.0, 2.0]]), torch.full((1, 3), 0.5), torch.tensor([0.01]))
    budget = 19.5 / (40 * 30)
    assert gaussian_map.densify_colour_error(0, camera, images, None, threshold=0.2, fraction=budget) == 19
    added = gaussian_map.gaussians(rows=torch.arange(1, 20))
    pixels = camera.project(added.means_m.double().numpy(), added.means_m[:, 2].double().numpy())
    assert np.all((pixels[:, 0] >= 9.5) & (pixels[:, 0] <= 14.5) & (pixels[:, 1] >= 9.5) & (pixels[:, 1] <= 13.5))
    np.testing.assert_allclose(torch.exp(added.log_radii_m).numpy(), 2.0 / camera.mean_focal_px, rtol=1e-5)
    np.testing.assert_allclose(added.rgb.numpy(), 1.0)
    assert gaussian_map.densify_colour_error(0, camera, images, None, threshold=0.0, fraction=1.0) == 0  # 0: off


def test_frames_between_views_are_evenly_spaced_among_the_usable_ones():
    usable = np.ones(30, bool)
    usable[[5, 10, 15]] = False
    # Views at 0, 12 and 20 (any order); after the last view, up to the end.
    assert frames_between_views([12, 0, 20], usable, 2) == [3, 8, 14, 18, 23, 27]
    assert frames_between_views([0, 12, 20], usable, 1) == [6, 17, 25]
    # Where a gap has no more usable frames than asked for, all of them; views next to each other give none.
    assert frames_between_views([0, 3, 4], usable, 2) == [1, 2, 12, 24]
    assert frames_between_views([0, 1], np.ones(2, bool), 3) == []
    assert frames_between_views([0, 10], usable, 0) == []


def test_frames_between_views_take_the_sharpest_frame_of_each_share_where_frames_are_scored():
    usable = np.ones(30, bool)
    usable[[5, 10, 15]] = False
    sharpness = np.full(30, np.nan)
    # Gap 0-12 (usable 1-4, 6-9, 11): shares 1-4 and 6-11; gap 12-20: shares 13-16 and 17-19; after 20: 21-24, 25-29.
    sharpness[[1, 2, 3, 4]] = [5.0, 9.0, 1.0, 2.0]
    sharpness[[6, 7, 8, 9, 11]] = [1.0, 1.0, 1.0, 1.0, 3.0]
    sharpness[[14, 16]] = [4.0, 7.0]
    sharpness[15] = 100.0  # not usable (held out): never chosen however sharp
    sharpness[22] = 0.5
    # Shares 17-19 and 25-29 hold no scored frame: their middles, as without sharpness.
    assert frames_between_views([12, 0, 20], usable, 2, sharpness) == [2, 11, 16, 18, 22, 27]
    assert frames_between_views([12, 0, 20], usable, 2, np.full(30, np.nan)) == frames_between_views([12, 0, 20], usable, 2)
    # After 4: shares 6-18 and 19-29, whose sharpest scored frames are 16 and 22.
    assert frames_between_views([0, 3, 4], usable, 2, sharpness) == [1, 2, 16, 22]


@pytest.mark.slow
def test_frames_between_views_sharpen_the_map_where_no_view_is(synthetic_sequence_dir, tmp_path, monkeypatch):
    """Fitted to the tracked frames between its views too, the map renders the held-out frames (every 3rd, never
    read by the pass) closer to what they show than fitted to the views alone, at the same rounds and even at the
    same number of steps (three times the rounds over the views alone)."""
    sequence = open_sequence(synthetic_sequence_dir, max_frames=24)
    stage, _ = coarse_stage(sequence, tmp_path)
    held_out = list(range(0, len(sequence), 3))
    tracking = types.SimpleNamespace(trajectory=sequence.ground_truth, tracked=np.ones(len(sequence), bool),
                                     tracked_by_depth=None)
    tracking.tracked[13] = False  # a lost frame is not fitted either

    def held_out_l1() -> float:
        errors = []
        for index in held_out:
            rendered = stage.map.render(sequence.camera, sequence.ground_truth.world_from_camera[index]).rgb
            errors.append(float((rendered.detach().clamp(0.0, 1.0) - resize_frame(sequence[index], 1.0).rgb).abs().mean()))
        return float(np.mean(errors))

    state = copy.deepcopy(stage.state_dict())
    stage.mapper_config = dataclasses.replace(stage.mapper_config, sharp_frames_between=2)
    frames = stage.frames_between(tracking, held_out)
    # Views at 0, 6, 12, 18: two of the four usable frames between each (14, 16, 17 where 13 is lost and 15 held out).
    assert [frame.frame_index for frame in frames] == [2, 5, 8, 11, 14, 17, 20, 23]
    assert all(isinstance(frame, FrameBetween) and frame.exposure_path is None for frame in frames)
    np.testing.assert_allclose(frames[0].world_from_camera, sequence.ground_truth.world_from_camera[2], atol=1e-9)
    after = {}
    for rounds, fitted in ((4, []), (12, []), (4, frames)):
        stage.load_state_dict(copy.deepcopy(state))
        stage.mapper_config = dataclasses.replace(stage.mapper_config, sharp_iterations_per_view=rounds)
        read = []
        getitem = type(sequence).__getitem__
        monkeypatch.setattr(type(sequence), "__getitem__", lambda self, index: read.append(index) or getitem(self, index))
        stage.sharpen(fitted)
        monkeypatch.undo()
        assert sorted(set(read)) == sorted({view.frame_index for view in stage.views} | {f.frame_index for f in fitted})
        after[rounds, len(fitted)] = held_out_l1()
    assert after[4, len(frames)] < 0.95 * after[4, 0] and after[4, len(frames)] < 0.98 * after[12, 0], after
