"""Sensor failures mid-run (whole frames of invalid depth, a covered lens): the run goes on, counts them, recovers."""

from __future__ import annotations

import re
import shutil

import numpy as np
import pytest

from pipelines.reconstruct import reconstruct
from tambridge.config import load_config
from tambridge.evaluation.trajectory import evaluate_trajectory
from tambridge.io.synthetic import blank_frames
from tambridge.io.tum import open_sequence
from tambridge.trajectory import Trajectory

NO_DEPTH = (8, 9, 10)
BLACK = (18, 19, 20)
OPTIONS = ("mapper.enabled=false", "mesh.enabled=false", "frontend.orb.mapping_thread=false")


def _ate_m(trajectory: Trajectory, ground_truth: Trajectory, frames: np.ndarray) -> float:
    return evaluate_trajectory(Trajectory(trajectory.timestamps_s[frames], trajectory.world_from_camera[frames]),
                               ground_truth).ate_rmse_m


def test_blank_frames_are_invalid_depth_and_black_colour(synthetic_sequence_dir, tmp_path):
    folder = tmp_path / "damaged"
    shutil.copytree(synthetic_sequence_dir, folder)
    blank_frames(folder, depth_frames=[2], colour_frames=[3])
    damaged, clean = open_sequence(folder), open_sequence(synthetic_sequence_dir)
    assert not damaged[2].depth_m.any() and damaged[2].rgb.any()
    assert not damaged[3].rgb.any() and np.array_equal(damaged[3].depth_m, clean[3].depth_m)
    assert np.array_equal(damaged[4].rgb, clean[4].rgb)


@pytest.mark.slow
def test_run_counts_lost_frames_and_recovers(synthetic_sequence_dir, tmp_path):
    folder = tmp_path / "damaged"
    shutil.copytree(synthetic_sequence_dir, folder)
    blank_frames(folder, depth_frames=NO_DEPTH, colour_frames=BLACK)
    config = load_config(None, OPTIONS)
    damaged = reconstruct(folder, tmp_path / "damaged_out", config, progress=False)
    clean = reconstruct(synthetic_sequence_dir, tmp_path / "clean_out", config, progress=False)

    log = (tmp_path / "damaged_out" / "run.log").read_text()
    lost = {int(number) for number in re.findall(r"frame (\d+) \(t=[0-9.]+\): tracking lost", log)}
    by_depth = {int(number) for number in re.findall(r"frame (\d+) \(t=[0-9.]+\): tracked by its depth alone", log)}
    # A covered lens has no keypoints: those frames are tracked by their depth while the last keyframe's surface
    # holds them (the loop turns 12 degrees a frame, so not for long: the first one, 65 % of its depth on the
    # surface, the next 58 %), then lost; frames without depth still track from colour.
    assert BLACK[0] in by_depth and by_depth | lost == set(BLACK) and not by_depth & lost
    assert lost.isdisjoint(NO_DEPTH)
    assert damaged.metrics.frames_lost == len(lost)
    assert damaged.metrics.frames_tracked_by_depth == len(by_depth)
    assert damaged.metrics.frames_without_depth == len(NO_DEPTH)
    assert clean.metrics.frames_without_depth == 0
    assert {int(n) for n in re.findall(r"frame (\d+) \(t=[0-9.]+\): no valid depth", log)} == set(NO_DEPTH)
    recovered = [int(n) for n in re.findall(r"frame (\d+) \(t=[0-9.]+\): tracking recovered", log)]
    assert any(max(BLACK) < n <= max(BLACK) + 3 for n in recovered), recovered
    assert len(damaged.trajectory.timestamps_s) == len(open_sequence(folder))

    # Tracking recovers: the frames with a working sensor are about as accurate as in the undamaged run.
    ground_truth = open_sequence(folder).ground_truth
    good = np.setdiff1d(np.arange(len(damaged.trajectory.timestamps_s)), NO_DEPTH + BLACK)
    after = good[good > max(BLACK)]
    assert _ate_m(damaged.trajectory, ground_truth, good) < _ate_m(clean.trajectory, ground_truth, good) + 0.005
    assert _ate_m(damaged.trajectory, ground_truth, after) < _ate_m(clean.trajectory, ground_truth, after) + 0.005
    # A lost frame lies on the path between the tracked frames around it (Trajectory.bridged): within 3 cm here, where
    # the constant-velocity prediction from the frames before it alone put the second of the two 6.6 cm off.
    errors_m = evaluate_trajectory(damaged.trajectory, ground_truth).ate_errors_m
    assert len(errors_m) == len(damaged.trajectory.timestamps_s)
    assert errors_m[sorted(lost)].max() < 0.03, errors_m[sorted(lost)]


def test_colour_images_without_depth_are_counted_and_many_of_them_warned_of(synthetic_sequence_dir, tmp_path):
    """A depth.txt cut short: the last 20 colour images have no depth image within 20 ms. The run leaves them out,
    says so on the console and counts them in metrics.json."""
    folder = tmp_path / "short_depth"
    shutil.copytree(synthetic_sequence_dir, folder)
    lines = (folder / "depth.txt").read_text().splitlines()
    listed = [line for line in lines if not line.startswith("#")]
    (folder / "depth.txt").write_text("\n".join([line for line in lines if line.startswith("#")] + listed[:10]) + "\n")
    config = load_config(None, [*OPTIONS, "input.max_frames=3"])
    result = reconstruct(folder, tmp_path / "out", config, progress=False)
    assert result.metrics.colour_images_without_depth == len(listed) - 10 == 20
    log = (tmp_path / "out" / "run.log").read_text()
    assert ("WARNING tambridge.pipelines.reconstruct: 20 of the 30 colour images of rgb.txt have no depth image within "
            "0.02 s: left out; check depth.txt") in log


def test_a_depth_scale_off_by_a_factor_is_warned_of_where_there_is_ground_truth(synthetic_sequence_dir, tmp_path, caplog):
    """Twice the depth scale halves every depth (the median still plausible) and so the whole trajectory: the Sim(3)
    fit to the ground truth says so, with the scale that fits."""
    folder = tmp_path / "scaled"
    shutil.copytree(synthetic_sequence_dir, folder)
    camera = (folder / "camera.yaml").read_text()
    scale = float(re.search(r"depth_scale: *([0-9.e+]+)", camera).group(1))
    (folder / "camera.yaml").write_text(camera.replace(re.search(r"depth_scale: *[0-9.e+]+", camera).group(0),
                                                       f"depth_scale: {2 * scale}"))
    reconstruct(folder, tmp_path / "out", load_config(None, OPTIONS), progress=False)
    warning = re.search(r"the trajectory is ([0-9.]+) times the size of groundtruth\.txt's \(Sim\(3\) fit over [0-9.]+ m "
                        r"of path\): a depth_scale off by that factor\? depth_scale ([0-9.]+) would fit", caplog.text)
    assert warning and float(warning.group(1)) == pytest.approx(0.5, abs=0.02), caplog.text
    assert float(warning.group(2)) == pytest.approx(scale, rel=0.04)


def test_a_few_colour_images_without_depth_at_the_start_are_no_warning():
    from pipelines.reconstruct import many_without_depth

    # TUM fr1/xyz's first 37 colour images leave 5 out (depth starts later), the whole 798 leave 6 out.
    assert not many_without_depth(5, 37) and not many_without_depth(6, 798)
    assert many_without_depth(18, 37) and many_without_depth(20, 30) and not many_without_depth(12, 798)
