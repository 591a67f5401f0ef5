"""The map as exported: scores of splats.ply reloaded, metrics.json round trip, and exposures that keep true colour."""

import shutil

import cv2
import numpy as np
import pytest
import torch

from tambridge.bridge.config import BridgeConfig
from tambridge.evaluation.exported import ExportedMap, colour_ratio, score_exported
from tambridge.evaluation.metrics import (
    SCHEMA_VERSION,
    BridgeMetrics,
    DeviceMetrics,
    ExportedViewScores,
    MapMetrics,
    RenderingMetrics,
    RunMetrics,
    ScoredAgainst,
    ViewScores,
    read_metrics,
    write_metrics,
)
from tambridge.errors import TambridgeError
from tambridge.evaluation.rendering import psnr_db, ssim_value
from tambridge.export.splats import save_ply
from tambridge.frontend.contract import KeyframeEvent
from tambridge.gaussians.config import ExposureAnchor, MapperConfig
from tambridge.gaussians.mapper import MIN_EXPOSURE_FIT_PIXELS, ViewExposure, backproject, fit_exposure
from tambridge.gaussians.model import GaussianTensors
from tambridge.gaussians.rasterizer import render
from tambridge.io.synthetic import SynthOptions, write_synthetic_sequence
from tambridge.io.tum import open_sequence
from tambridge.mapping.stage import MappingStage
from tambridge.runlog import RunLog
from tambridge.threads import TORCH_THREADS, compute_threads
from tambridge.trajectory import Trajectory, write_tum_trajectory


@pytest.fixture(autouse=True)
def two_kernel_threads():
    with compute_threads(TORCH_THREADS, 2):
        yield


@pytest.fixture(scope="module")
def small_sequence_dir(tmp_path_factory):
    """A noise-free 16-frame 80x60 loop with exact ground truth."""
    folder = tmp_path_factory.mktemp("exported") / "room"
    write_synthetic_sequence(folder, SynthOptions(frame_count=16, width=80, height=60))
    return folder


def frame_splats(sequence, frame_index: int, colour_scale: float) -> GaussianTensors:
    """Opaque Gaussians on every pixel of one frame, coloured by the frame's colours times ``colour_scale``."""
    frame = sequence[frame_index]
    depth = torch.from_numpy(frame.depth_m)
    mask = depth > 0
    points = backproject(depth, sequence.camera, mask).double().numpy()
    pose = sequence.ground_truth.world_from_camera[frame_index]
    world = points @ pose[:3, :3].T + pose[:3, 3]
    rgb = torch.from_numpy(frame.rgb[mask.numpy()].astype(np.float32) / 255.0) * colour_scale
    radii = torch.from_numpy(points[:, 2] / sequence.camera.mean_focal_px * 1.5).float()
    return GaussianTensors(torch.from_numpy(world).float(), rgb, torch.log(radii), torch.full((len(rgb),), 5.0))


def test_scores_as_exported_are_those_of_a_direct_render_of_the_map_written(small_sequence_dir, tmp_path):
    """splats.ply and trajectory.txt written, read back and scored: the figures of rendering the Gaussians that
    were written, at the poses that were written, against the frames."""
    sequence = open_sequence(small_sequence_dir)
    gaussians = frame_splats(sequence, 0, 0.8)
    poses = sequence.ground_truth.world_from_camera
    save_ply(tmp_path / "splats.ply", gaussians)
    write_tum_trajectory(tmp_path / "trajectory.txt", Trajectory(sequence.timestamps_s, poses))
    config = MapperConfig(resolution_scale=0.5)
    exported = ExportedMap.from_run(tmp_path, config)
    frames = [1, 2, 3]
    scores = score_exported(exported, sequence, frames, (0, 3), config)
    direct = [(render(gaussians, sequence.camera, poses[index]).rgb.clamp(0, 1).numpy(),
               sequence[index].rgb.astype(np.float32) / 255.0) for index in frames]
    assert scores.frames == 3
    assert scores.psnr_db == pytest.approx(np.mean([psnr_db(r, o) for r, o in direct]), abs=1e-4)
    assert scores.ssim == pytest.approx(np.mean([ssim_value(r, o) for r, o in direct]), abs=1e-5)
    halved = [(cv2.resize(r, (40, 30), interpolation=cv2.INTER_AREA), cv2.resize(o, (40, 30), interpolation=cv2.INTER_AREA))
              for r, o in direct]
    assert scores.ssim_mapping_resolution == pytest.approx(np.mean([ssim_value(r, o) for r, o in halved]), abs=1e-5)
    # The splats of frame 0 hold its colours at 0.8: a viewer at frame 0 shows them 20 % darker.
    np.testing.assert_allclose(scores.first_view_colour_ratio, 0.8, atol=0.02)
    assert scores.first_view_colour_ratio == colour_ratio(exported, sequence, 0)


def _metrics(exported: ExportedViewScores) -> RunMetrics:
    views = ViewScores(frames=4, psnr_db=24.0, ssim=0.8, lpips=None)
    return RunMetrics(
        sequence="seq", frames=30, keyframes=5, frontend="orb", frames_lost=0, frames_relocalised=0,
        frames_without_depth=0, loops_closed=0, keyframes_culled=0, frontend_seconds_per_stage={}, seconds_total=10.0,
        fps_end_to_end=3.0, seconds_per_stage={}, fps_per_stage={}, peak_memory_mb=500.0, peak_memory_mb_tracking=400.0,
        warnings=0, trajectory=None, trajectory_unavailable="no ground truth", device=DeviceMetrics(device="cpu"),
        map=MapMetrics(rendering=RenderingMetrics(novel_views=views, mapping_views=views, novel_views_exported=exported,
                                                  scored_against=ScoredAgainst.input, novel_views_sharper_half=views),
                       gaussians=1000, mapping_views=5, mapping_resolution=[160, 120],
                       bridge=BridgeMetrics(enabled=True, view_selection={"FIRST": 1}, refined_views=4,
                                            mean_loss_initial=0.1, mean_loss_final=0.05)))


def test_metrics_with_the_exported_scores_round_trip_and_older_files_are_refused(tmp_path):
    path = tmp_path / "metrics.json"
    for exported in (ExportedViewScores(frames=4, psnr_db=23.5, ssim=0.79, lpips=None, ssim_mapping_resolution=0.9,
                                        first_view_colour_ratio=[0.98, 1.0, 1.01], last_view_colour_ratio=[1.02, 1.0, 0.99]),
                     ExportedViewScores(frames=0, psnr_db=None, ssim=None, lpips=None, ssim_mapping_resolution=None,
                                        first_view_colour_ratio=None, last_view_colour_ratio=None)):
        metrics = _metrics(exported)
        write_metrics(path, metrics)
        assert read_metrics(path) == metrics
    written = path.read_text()
    assert f'"schema_version": {SCHEMA_VERSION},' in written and '"novel_views_exported": {' in written
    # A file of schema 1 (before the exported scores) is refused in one line that says what to do.
    path.write_text(written.replace(f'"schema_version": {SCHEMA_VERSION}', '"schema_version": 1'))
    with pytest.raises(TambridgeError, match="schema_version 1; this tambridge reads schema_version .*: run reconstruct again"):
        read_metrics(path)
    path.write_text(written.replace('"ssim_mapping_resolution"', '"ssim_low"'))
    with pytest.raises(TambridgeError, match="lacks key 'rendering.novel_views_exported.ssim_mapping_resolution'"):
        read_metrics(path)


def gained_sequence(source, folder, gains: np.ndarray):
    """A copy of the sequence in ``source`` whose frame k's colours are scaled by ``gains[k]`` (the camera's
    exposure changing along the sequence)."""
    shutil.copytree(source, folder)
    sequence = open_sequence(folder)
    for path, gain in zip(sequence.rgb_paths, gains):
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float64)
        cv2.imwrite(str(path), np.clip(image * gain + 0.5, 0, 255).astype(np.uint8))
    return open_sequence(folder)


def test_rebased_exposures_give_the_same_colours_of_the_recoloured_map():
    generator = torch.Generator().manual_seed(0)
    colours = torch.rand((50, 3), generator=generator) * 0.6 + 0.2
    exposure = ViewExposure(torch.randn((2, 3), generator=generator) * 0.1, learning_rate=1e-2)
    reference = torch.randn((2, 3), generator=generator) * 0.1
    before = exposure.apply(colours).detach()
    exposure.rebase(reference)
    recoloured = ViewExposure(reference, frozen=True).apply(colours)
    torch.testing.assert_close(exposure.apply(recoloured).detach(), before, atol=1e-6, rtol=0)


def test_the_fitted_exposure_is_the_least_squares_line_of_each_channel():
    """Against numpy's least squares on the masked pixels, channel by channel; an exact affine change of the colours
    is recovered, and a fit without enough pixels or with a falling line gives none."""
    generator = torch.Generator().manual_seed(0)
    rendered = torch.rand((30, 40, 3), generator=generator)
    gain, bias = torch.tensor([0.8, 1.1, 1.3]), torch.tensor([0.05, -0.02, 0.0])
    observed = rendered * gain + bias + 0.05 * torch.randn((30, 40, 3), generator=generator)
    mask = torch.rand((30, 40), generator=generator) > 0.3
    fitted = fit_exposure(rendered, observed, mask)
    for channel in range(3):
        design = np.stack([rendered[..., channel][mask].numpy(), np.ones(int(mask.sum()))], axis=1).astype(np.float64)
        (line_gain, line_bias), *_ = np.linalg.lstsq(design, observed[..., channel][mask].numpy().astype(np.float64), rcond=None)
        np.testing.assert_allclose([np.exp(float(fitted[0, channel])), float(fitted[1, channel])], [line_gain, line_bias],
                                   rtol=1e-5, atol=1e-6)
    exact = fit_exposure(rendered, rendered * gain + bias, mask)
    torch.testing.assert_close(ViewExposure(exact, frozen=True).apply(rendered), rendered * gain + bias, atol=1e-5, rtol=0)
    few = torch.zeros((30, 40), dtype=torch.bool)
    few.view(-1)[: MIN_EXPOSURE_FIT_PIXELS - 1] = True
    assert fit_exposure(rendered, observed, few) is None
    assert fit_exposure(rendered, 1.0 - rendered, mask) is None


def test_reset_exposure_renders_the_new_parameters_and_steps_from_fresh_moments():
    exposure = ViewExposure(learning_rate=0.1)
    (-10.0 * exposure.apply(torch.ones((2, 2, 3))).sum()).backward()
    exposure.step()
    exposure.reset(torch.zeros((2, 3)))
    torch.testing.assert_close(exposure.apply(torch.full((2, 2, 3), 0.5)).detach(), torch.full((2, 2, 3), 0.5))
    exposure.apply(torch.ones((2, 2, 3))).sum().backward()
    exposure.step()
    # Adam's first step from fresh moments moves every parameter by the learning rate, against its gradient.
    torch.testing.assert_close(exposure.parameters.detach(), torch.full((2, 3), -0.1))


@pytest.mark.slow
@pytest.mark.parametrize("anchor", [ExposureAnchor.median, ExposureAnchor.first_view])
def test_exposures_keep_the_map_in_true_colour_when_the_camera_exposure_changes(small_sequence_dir, tmp_path, anchor):
    """The frames' gain follows exp(0.15 cos(2 pi k / 16)): 1.16 at the first frame, 0.86 half way, 1 at the median
    view. Mapped at ground-truth poses, the map's own colours (what splats.ply holds) are the true ones at the first
    and at a middle view; anchored at the first view instead, the map takes that view's exposure. No sharpening
    pass: it fits the frames as recorded, gains included, by design (test_sharpening.py)."""
    gains = np.exp(0.15 * np.cos(2 * np.pi * np.arange(16) / 16))
    true_colour = open_sequence(small_sequence_dir)
    sequence = gained_sequence(small_sequence_dir, tmp_path / "gained", gains)
    config = MapperConfig(resolution_scale=1.0, iterations=20, exposure_anchor=anchor, sharp_iterations_per_view=0)
    poses = sequence.ground_truth.world_from_camera
    run_log = RunLog(tmp_path / "run.log")
    try:
        stage = MappingStage(sequence, config, BridgeConfig(enabled=False), run_log)
        keyframe_poses = {}
        for keyframe_id, index in enumerate(range(0, 16, 2)):
            keyframe_poses[keyframe_id] = poses[index]
            event = KeyframeEvent(keyframe_id, index, 0.0, poses[index], np.zeros((0, 3)), np.zeros((0, 2)),
                                  np.zeros(0, np.int64), 0, 0)
            stage.on_keyframe(event, sequence[index], dict(keyframe_poses))
        stage.finish(keyframe_poses)
    finally:
        run_log.close()
    exported = ExportedMap(stage.map.world_gaussians(), poses)
    ratios = {index: np.mean(colour_ratio(exported, true_colour, index)) for index in (0, 8)}
    if anchor is ExposureAnchor.median:
        # finish anchors after its last steps: the median view's exposure is the identity (to rounding).
        median = torch.quantile(torch.stack([view.exposure.parameters.detach() for view in stage.views]), 0.5, dim=0)
        torch.testing.assert_close(median, torch.zeros((2, 3)), atol=2e-4, rtol=0)
        # The bound leaves room for the prior's pull, which holds the views' exposures a little short of the frames'
        # gains (the map then takes the rest), and for the views' exposures being estimated, not known.
        assert abs(ratios[0] - 1.0) < 0.04 and abs(ratios[8] - 1.0) < 0.04, ratios
    else:
        assert ratios[0] > 1.1, ratios
