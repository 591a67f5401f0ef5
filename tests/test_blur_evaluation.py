"""Motion-blurred synthetic sequences: the synth command's options, and the evaluation against their sharp frames."""

import contextlib
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from cli import main
from tambridge.errors import SequenceFormatError
from tambridge.evaluation.mapping import score_views, scores_of_frames, sharper_half
from tambridge.evaluation.rendering import reference_rgb
from tambridge.images import sharpness
from tambridge.io.synthetic import RotationBursts, SynthOptions, write_synthetic_sequence
from tambridge.io.tum import GT_RGB_FOLDER, open_sequence
from tambridge.trajectory import read_tum_trajectory


def test_synth_command_takes_the_exposure_in_seconds_and_bursts(tmp_path):
    out = tmp_path / "blurred"
    result = CliRunner().invoke(main, ["synth", str(out), "--frames", "30", "--size", "32x24", "--motion-blur", "0.02",
                                       "--blur-subframes", "2", "--rotation-bursts", "1", "--burst-duration", "0.5"])
    assert result.exit_code == 0, result.output
    assert len(list((out / GT_RGB_FOLDER).iterdir())) == len(list((out / "rgb").iterdir())) == 30
    expected = SynthOptions(30, 32, 24, exposure_s=0.02, bursts=RotationBursts(1, duration_s=0.5)).path.poses(np.arange(30))
    np.testing.assert_allclose(read_tum_trajectory(out / "groundtruth.txt").world_from_camera, expected, atol=1e-6)
    refused = CliRunner().invoke(main, ["synth", str(tmp_path / "no"), "--frames", "30", "--rotation-bursts", "2"])
    assert refused.exit_code != 0 and "do not fit" in refused.output and not (tmp_path / "no").exists()


@pytest.fixture(scope="module")
def blurred_dir(tmp_path_factory):
    """26 frames, 64x48, 1/30 s exposure, one 0.42 s burst: blurred inputs beside their sharp gt_rgb/."""
    folder = tmp_path_factory.mktemp("blurred") / "room"
    write_synthetic_sequence(folder, SynthOptions(26, 64, 48, exposure_s=1 / 30, bursts=RotationBursts(1, 120.0, 0.42)))
    return folder


def _mapping_rendering(sequence, image_of_frame):
    """A stand-in for a MappingStage whose map renders, at frame i's pose, ``image_of_frame(i)`` (uint8)."""
    def render(camera, world_from_camera):
        image = image_of_frame(int(round(world_from_camera[0, 3])))
        return SimpleNamespace(rgb=torch.from_numpy(image.astype(np.float32) / 255.0))
    return SimpleNamespace(sequence=sequence, map=SimpleNamespace(render=render), views=[], threads=contextlib.nullcontext)


def _pose_coding_frames(count):
    """Poses whose x translation is the frame index (read back by the stand-in map)."""
    poses = np.tile(np.eye(4), (count, 1, 1))
    poses[:, 0, 3] = np.arange(count)
    return poses


def test_renders_are_scored_against_the_sharp_frames_where_a_sequence_has_them(blurred_dir, synthetic_sequence_dir):
    sequence = open_sequence(blurred_dir)
    assert sequence.has_sharp_rgb
    names = [path.name for path in sequence.rgb_paths]
    frames = list(range(0, 16, 3))
    for index in frames:
        np.testing.assert_array_equal(sequence.sharp_rgb(index), cv2.imread(str(blurred_dir / GT_RGB_FOLDER / names[index]))[:, :, ::-1])
        assert np.abs(sequence.sharp_rgb(index).astype(int) - sequence[index].rgb).mean() > 1.0
    poses = _pose_coding_frames(len(sequence))
    perfect = _mapping_rendering(sequence, sequence.sharp_rgb)  # a map that renders exactly the sharp frames
    against_sharp = score_views(perfect, poses, frames)
    against_input = score_views(perfect, poses, frames, against_sharp=False)
    assert against_sharp.psnr_db == [float("inf")] * len(frames) and against_sharp.ssim == pytest.approx([1.0] * len(frames))
    assert all(10.0 < value < 40.0 for value in against_input.psnr_db), against_input.psnr_db
    # A map that renders the blurred inputs is perfect against them only.
    blurred = score_views(_mapping_rendering(sequence, lambda index: sequence[index].rgb), poses, frames, against_sharp=False)
    assert blurred.psnr_db == [float("inf")] * len(frames)
    # Without gt_rgb/, the input frames are the reference.
    plain = open_sequence(synthetic_sequence_dir)
    assert not plain.has_sharp_rgb
    np.testing.assert_array_equal(reference_rgb(plain, 3), plain[3].rgb)
    with pytest.raises(SequenceFormatError, match="gt_rgb"):
        plain.sharp_rgb(3)


def test_sharper_half_is_the_half_of_higher_input_sharpness(blurred_dir):
    sequence = open_sequence(blurred_dir)
    frames = [1, 2, 4, 6, 7, 9, 11, 13, 15, 18, 21, 22, 24]
    half = sharper_half(sequence, frames)
    scores = {index: sharpness(sequence[index].rgb) for index in frames}
    assert len(half) == 7 and half == sorted(half) and set(half) <= set(frames)
    assert min(scores[i] for i in half) > max(scores[i] for i in frames if i not in half)
    # The sharper inputs are the less blurred ones: nearer their sharp frames (PSNR of the sharp frame against them).
    scores_all = score_views(_mapping_rendering(sequence, sequence.sharp_rgb), _pose_coding_frames(26), frames,
                             against_sharp=False)
    subset = scores_of_frames(scores_all, half)
    rest = scores_of_frames(scores_all, [i for i in frames if i not in half])
    assert subset.frame_indices == half and len(subset.psnr_db) == len(subset.ssim) == 7
    assert subset.psnr_db == [scores_all.psnr_db[frames.index(i)] for i in half]
    assert np.mean(subset.psnr_db) > np.mean(rest.psnr_db) + 1.0
    assert sharper_half(sequence, [5]) == [5] and sharper_half(sequence, []) == []


@pytest.mark.slow
def test_a_run_on_a_blurred_sequence_reports_scores_against_sharp_frames_and_inputs(tmp_path):
    from pipelines.reconstruct import reconstruct
    from tambridge.config import Config
    from tambridge.evaluation.metrics import read_metrics

    write_synthetic_sequence(tmp_path / "seq", SynthOptions(16, 128, 96, exposure_s=1 / 30, blur_subframes=4))
    config = Config()
    config.frontend.kind = "open3d"  # keyframes: the frames between them are novel views
    config.mesh.enabled = False
    # The scores' bookkeeping is under test, not the map: no blur-aware mapping, no sharpening pass, few Adam steps.
    config.bridge.blur_exposure_s = 0.0
    config.mapper.sharp_iterations_per_view = 0
    config.mapper.iterations = 4
    config.mapper.final_iterations_per_view = 1
    config.evaluation.novel_view_every = 1
    reconstruct(tmp_path / "seq", tmp_path / "out", config, progress=False)
    rendering = read_metrics(tmp_path / "out" / "metrics.json").map.rendering
    assert rendering.scored_against == "sharp_ground_truth"
    novel, against_input, half = rendering.novel_views, rendering.novel_views_against_input, rendering.novel_views_sharper_half
    assert novel.frames == against_input.frames >= 2 and half.frames == (novel.frames + 1) // 2
    assert np.isfinite([novel.psnr_db, against_input.psnr_db, half.psnr_db]).all()
    assert novel.psnr_db != against_input.psnr_db
