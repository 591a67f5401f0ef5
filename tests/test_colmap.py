"""COLMAP on a synthetic sequence: the Sim(3)-aligned trajectory lies within 2 cm of the truth."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipelines.colmap import colmap
from tambridge.errors import TambridgeError
from tambridge.evaluation.colmap import ColmapError, ColmapOptions, is_monocular_trajectory_file, run_colmap
from tambridge.io.synthetic import SynthOptions, default_camera, write_synthetic_sequence
from tambridge.trajectory import read_tum_trajectory

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def sequence_320(tmp_path_factory) -> Path:
    """A 20-frame 320x240 loop: SIFT on 160x120 finds too few features for a dependable model."""
    folder = tmp_path_factory.mktemp("colmap") / "room320"
    write_synthetic_sequence(folder, SynthOptions(frame_count=20, width=320, height=240))
    return folder


@pytest.mark.slow
def test_colmap_trajectory_within_2cm_after_sim3(sequence_320, tmp_path):
    run = colmap(sequence_320, tmp_path / "out", every=1, options=ColmapOptions(num_threads=2))
    assert run.metrics["registered"] == 20
    assert run.errors.pose_count == 20
    assert run.errors.ate_rmse_m < 0.02, run.errors.ate_rmse_m
    assert run.errors.ate_max_m < 0.03
    # Monocular: the scale is COLMAP's own, far from 1 in general, and the file says so.
    written = tmp_path / "out" / "trajectory.txt"
    assert is_monocular_trajectory_file(written)
    np.testing.assert_allclose(read_tum_trajectory(written).timestamps_s, run.trajectory.timestamps_s, atol=1e-6)
    assert json.loads((tmp_path / "out" / "metrics.json").read_text())["registered"] == 20
    assert (tmp_path / "out" / "trajectory.png").read_bytes()[:8] == PNG_SIGNATURE


def test_colmap_refuses_a_bad_output_folder_before_running(synthetic_sequence_dir, tmp_path):
    (tmp_path / "a_file").write_text("x")
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("x")
    for output, message in ((tmp_path / "a_file", "a_file is a file, not a folder"),
                            (tmp_path / "other", r"holds files this command did not write \(notes.txt\)")):
        with pytest.raises(TambridgeError, match=message):
            colmap(synthetic_sequence_dir, output, every=1)
    assert sorted(path.name for path in tmp_path.rglob("*")) == ["a_file", "notes.txt", "other"]
    # Too few frames for COLMAP: refused before anything of an earlier result goes, and no new folder made.
    (tmp_path / "earlier").mkdir()
    (tmp_path / "earlier" / "metrics.json").write_text("{}")
    for output in (tmp_path / "earlier", tmp_path / "new"):
        with pytest.raises(ColmapError, match=r"COLMAP needs at least 3 images, got 2; use a smaller --every or a larger --max-frames$"):
            colmap(synthetic_sequence_dir, output, every=15)
    assert (tmp_path / "earlier" / "metrics.json").read_text() == "{}" and not (tmp_path / "new").exists()


@pytest.mark.slow
def test_ground_truth_on_another_clock_leaves_colmaps_trajectory_and_says_why(sequence_320, tmp_path):
    sequence = tmp_path / "seq"
    shutil.copytree(sequence_320, sequence)
    truth = np.loadtxt(sequence / "groundtruth.txt")
    truth[:, 0] += 1000.0
    np.savetxt(sequence / "groundtruth.txt", truth, fmt="%.9f")
    run = colmap(sequence, tmp_path / "out", every=2, options=ColmapOptions(num_threads=2))
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert run.errors is None and metrics["trajectory"] is None
    assert metrics["trajectory_unavailable"].startswith("only 0 of ")
    assert len(read_tum_trajectory(tmp_path / "out" / "trajectory.txt")) == metrics["registered"] >= 3


def test_too_few_images_is_an_input_error():
    image = np.zeros((24, 32, 3), np.uint8)
    with pytest.raises(ColmapError, match="at least 3 images"):
        run_colmap([image, image], [0.0, 1.0], default_camera(32, 24))


def test_featureless_images_give_a_clear_error(tmp_path):
    images = [np.full((48, 64, 3), 128, np.uint8)] * 4
    with pytest.raises(ColmapError, match="smaller --every"):
        run_colmap(images, [0.0, 0.1, 0.2, 0.3], default_camera(64, 48), workspace=tmp_path)


def _moved(reference, scale: float, noise_m: float, seed: int):
    """The reference seen from another frame (rotated, shifted, scaled) with position noise: what an estimate looks like."""
    from tambridge.geometry import exp_se3
    from tambridge.trajectory import Trajectory

    rng = np.random.default_rng(seed)
    other_from_world = exp_se3(np.array([0.3, -0.2, 0.1, 0.2, 0.1, -0.3]))
    poses = []
    for pose in reference.world_from_camera:
        moved = other_from_world @ pose
        moved[:3, 3] = moved[:3, 3] * scale + rng.normal(0.0, noise_m, 3)
        poses.append(moved)
    return Trajectory(reference.timestamps_s, np.stack(poses))


def test_compare_aligns_monocular_files_with_sim3(tmp_path):
    from pipelines.compare import compare_files
    from tambridge.evaluation.colmap import write_monocular_trajectory
    from tambridge.io.synthetic import loop_path
    from tambridge.trajectory import Trajectory, write_tum_trajectory

    reference = Trajectory(np.arange(40) / 30.0, loop_path(40))
    write_tum_trajectory(tmp_path / "gt.txt", reference)
    write_tum_trajectory(tmp_path / "rgbd.txt", _moved(reference, 1.0, 0.002, seed=0))
    write_monocular_trajectory(tmp_path / "colmap.txt", _moved(reference, 0.25, 0.001, seed=1))
    write_tum_trajectory(tmp_path / "mono_unmarked.txt", _moved(reference, 0.25, 0.001, seed=1))
    paths = [tmp_path / name for name in ("rgbd.txt", "colmap.txt", "mono_unmarked.txt")]

    comparison = compare_files(tmp_path / "gt.txt", paths, sim3_names=(), plot_path=tmp_path / "compare.png")
    rows = {Path(row["name"]).stem: row for row in comparison.rows()}
    assert rows["rgbd"]["alignment"] == "se3" and rows["rgbd"]["ate_rmse_cm"] < 0.5
    assert rows["colmap"]["alignment"] == "sim3" and rows["colmap"]["ate_rmse_cm"] < 1.0
    assert rows["colmap"]["scale"] == pytest.approx(4.0, rel=0.02)
    # Without the marker (or --sim3) a monocular trajectory is compared in its own scale: large error.
    assert rows["mono_unmarked"]["alignment"] == "se3" and rows["mono_unmarked"]["ate_rmse_cm"] > 5
    assert (tmp_path / "compare.png").read_bytes()[:8] == PNG_SIGNATURE
    table = comparison.table().splitlines()
    assert table[0].startswith("trajectory") and len(table) == 4

    named = compare_files(tmp_path / "gt.txt", paths[2:], sim3_names=("mono_unmarked",))
    assert named.rows()[0]["alignment"] == "sim3" and named.rows()[0]["ate_rmse_cm"] < 1.0


def test_compare_rejects_a_sim3_name_that_matches_nothing(tmp_path):
    from pipelines.compare import compare_files
    from tambridge.errors import TrajectoryFormatError
    from tambridge.io.synthetic import loop_path
    from tambridge.trajectory import Trajectory, write_tum_trajectory

    reference = Trajectory(np.arange(10) / 30.0, loop_path(10))
    write_tum_trajectory(tmp_path / "gt.txt", reference)
    with pytest.raises(TrajectoryFormatError) as refused:
        compare_files(tmp_path / "gt.txt", [tmp_path / "gt.txt"], sim3_names=("nope",))
    assert str(refused.value) == (f"--sim3 'nope' names none of the trajectories given ({tmp_path / 'gt.txt'}); give "
                                  "one's path or its file name without .txt")
    with pytest.raises(TrajectoryFormatError, match=rf"^{tmp_path / 'gt.txt'}: is the ground truth \(--gt\) and an estimate too"):
        compare_files(tmp_path / "gt.txt", [tmp_path / "gt.txt"])
    with pytest.raises(TrajectoryFormatError, match=rf"^{tmp_path / 'gt.txt'}: named twice; give each trajectory once$"):
        compare_files(tmp_path / "other.txt", [tmp_path / "gt.txt", tmp_path / "." / "gt.txt"])
    # A stem that two files share names neither.
    (tmp_path / "b").mkdir()
    write_tum_trajectory(tmp_path / "b" / "gt.txt", reference)
    with pytest.raises(TrajectoryFormatError, match=r"^--sim3 'gt' names 2 of the trajectories \(.*\); give the path of"):
        compare_files(tmp_path / "other.txt", [tmp_path / "gt.txt", tmp_path / "b" / "gt.txt"], sim3_names=("gt",))
    # The same file however its path is written, or its stem, is named.
    (tmp_path / "a").mkdir()
    write_tum_trajectory(tmp_path / "a" / "t.txt", reference)
    for name in (str(tmp_path / "a" / "." / "t.txt"), "t"):
        comparison = compare_files(tmp_path / "gt.txt", [tmp_path / "a" / "t.txt"], sim3_names=(name,))
        assert [errors.alignment for errors in comparison.errors.values()] == ["sim3"]


def test_compare_command_prints_one_row_per_file(tmp_path):
    from click.testing import CliRunner

    from cli import main
    from tambridge.evaluation.colmap import write_monocular_trajectory
    from tambridge.io.synthetic import loop_path
    from tambridge.trajectory import Trajectory, write_tum_trajectory

    reference = Trajectory(np.arange(20) / 30.0, loop_path(20))
    write_tum_trajectory(tmp_path / "gt.txt", reference)
    write_tum_trajectory(tmp_path / "a.txt", _moved(reference, 1.0, 0.001, seed=0))
    write_monocular_trajectory(tmp_path / "colmap.txt", _moved(reference, 0.5, 0.0005, seed=1))
    result = CliRunner().invoke(main, ["compare", "--gt", str(tmp_path / "gt.txt"), str(tmp_path / "a.txt"),
                                       str(tmp_path / "colmap.txt"), "--plot", str(tmp_path / "all.png")])
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert "se3" in lines[1] and "sim3" in lines[2]
    assert (tmp_path / "all.png").read_bytes()[:8] == PNG_SIGNATURE
