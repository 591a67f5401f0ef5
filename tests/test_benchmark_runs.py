"""Benchmarks that reach into the pipeline (they wrap its stages to score more than a run does) still run against
it: a short synthetic through ``benchmarks/sharp_splats.py``'s child run."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_sharp_splats_scores_the_map_before_and_after_the_pass_its_ceiling_and_limits(synthetic_sequence_dir, tmp_path):
    out = tmp_path / "run"
    child = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "sharp_splats.py"), "--child",
                            str(synthetic_sequence_dir), "default", "20", str(out), "10:0.01", "limits",
                            "--pass-variant", "same:mapper.sharp_w_colour_squared=10",
                            "--pass-variant", "l1:mapper.sharp_w_colour_squared=0"],
                           cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert child.returncode == 0, child.stderr[-3000:]
    row = json.loads(child.stdout.strip().splitlines()[-1])
    rendering = json.loads((out / "metrics.json").read_text())["rendering"]
    # "on" is the run's own map: its scores are metrics.json's, through the exposures and as splats.ply reloads it.
    assert row["on"]["psnr"] == pytest.approx(rendering["novel_views"]["psnr_db"], abs=1e-9)
    assert row["on"]["psnr_exp"] == pytest.approx(rendering["novel_views_exported"]["psnr_db"], abs=0.01)
    # "off" is the map before the pass, pruned as the run prunes after it: the pass adds no Gaussians by default,
    # but it moves opacities, so the prune may remove a few others.
    assert abs(row["off"]["gaussians"] - row["on"]["gaussians"]) <= 0.01 * row["off"]["gaussians"]
    assert row["off"]["psnr"] != row["on"]["psnr"]
    assert row["frames"] == 20 and row["sharpening_seconds"] > 0 and 10 < row["off"]["psnr"] < 40
    # The silhouette classes split the pixels and the squared error between them; the synthetic room is measured
    # everywhere.
    for shares in (row["on"]["error_shares"], row["on"]["pixel_shares"]):
        assert sum(shares[name] for name in ("covered", "partial", "uncovered")) == pytest.approx(1.0, abs=1e-9)
        assert shares["unmeasured"] == 0.0
    assert row["on"]["pixel_shares"]["covered"] > 0.9
    # A pass again from the same map with the run's own settings is the run's pass, to the bit: same map, same
    # order of views and frames; another loss gives another map.
    same, l1 = row["variants"]["same"], row["variants"]["l1"]
    assert (same["psnr"], same["psnr_exp"], same["gaussians"]) == (row["on"]["psnr"], row["on"]["psnr_exp"],
                                                                  row["on"]["gaussians"])
    assert l1["psnr_exp"] != row["on"]["psnr_exp"] and l1["pass_seconds"] > 0
    # The ceiling starts from the run's map and is fitted to the very frames it is scored on: it must score higher
    # there, with Gaussians added by its densification.
    ceiling = row["ceiling"]
    assert ceiling["rounds"] == 10 and ceiling["gaussians_added"] > 0
    assert ceiling["gaussians"] == row["on"]["gaussians"] + ceiling["gaussians_added"]
    assert ceiling["psnr_exp"] > row["on"]["psnr_exp"] + 0.5 and ceiling["ssim_exp"] > row["on"]["ssim_exp"]
    # The limits are scored on the run's final map: as exported they are "on"'s; the best gain and bias of a frame
    # include the identity, so they never score lower; the refinement keeps the lowest loss it saw, which on these
    # drifting poses lies away from the start, centimetres away at most at the 40x30 mapping resolution.
    limits = row["limits"]
    assert limits["psnr_exp"] == pytest.approx(row["on"]["psnr_exp"], abs=1e-6)
    assert limits["psnr_affine"] >= limits["psnr_exp"]
    assert 0 < limits["pose_moved_mm"] < 50 and limits["psnr_pose"] != limits["psnr_exp"]
    assert abs(limits["psnr_pose"] - limits["psnr_exp"]) < 1.0


def kernel_benchmark_rows(script: str, arguments: list[str], tmp_path: Path) -> list[dict]:
    """The rows a kernel-against-twin benchmark (``benchmarks/SCRIPT``) writes with ``arguments`` and two repeats."""
    output = tmp_path / "result.json"
    child = subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), *arguments, "--repeats", "2",
                            "--output", str(output)], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert child.returncode == 0, child.stderr[-3000:]
    return json.loads(output.read_text())["rows"]


def test_ssim_benchmark_times_the_kernel_and_its_twin_and_finds_them_equal(tmp_path):
    rows = kernel_benchmark_rows("ssim.py", ["--resolutions", "40x30", "64x48"], tmp_path)
    assert [row["resolution"] for row in rows] == ["40x30", "64x48"]
    assert all(row["kernel_ms"] > 0 and row["twin_ms"] > 0 for row in rows)
    assert all(row["value_difference"] < 1e-6 and row["gradient_difference_relative"] < 1e-5 for row in rows)


def test_adam_benchmark_times_the_kernel_and_its_twin_and_finds_them_equal(tmp_path):
    rows = kernel_benchmark_rows("adam.py", ["--counts", "300", "1000"], tmp_path)
    assert [row["gaussians"] for row in rows] == [300, 1000]
    assert all(row["kernel_ms"] > 0 and row["twin_ms"] > 0 for row in rows)
    # Float32 rounding of the twin's bias corrections, against steps of the size of the learning rates.
    assert all(row["parameter_difference_relative"] < 1e-3 for row in rows)


def test_turns_benchmark_tracks_a_segment_as_a_sequence_of_its_own(synthetic_sequence_dir, tmp_path):
    """``benchmarks/turns.py`` on frames 5-24 of the synthetic loop: the segment folder holds those frames and the
    ground truth of their span, and the run scores them; Sim(3) has one more degree of freedom than SE(3), so its
    least-squares ATE is never the larger."""
    from benchmarks.turns import write_segment
    from tambridge.io.tum import read_file_list
    from tambridge.trajectory import read_tum_trajectory

    segment = write_segment(synthetic_sequence_dir, 5, 25, tmp_path / "segment")
    rgb = read_file_list(segment / "rgb.txt")
    source = read_file_list(synthetic_sequence_dir / "rgb.txt")[5:25]
    assert [name for _, name in rgb] == [name for _, name in source]
    assert all((segment / name).is_file() for _, name in rgb)
    truth_stamps = read_tum_trajectory(segment / "groundtruth.txt").timestamps_s
    assert truth_stamps[0] >= rgb[0][0] - 0.02 and truth_stamps[-1] <= rgb[-1][0] + 0.02
    output = tmp_path / "turns.json"
    child = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "turns.py"), "--sequence",
                            str(synthetic_sequence_dir), "--segments", "5-25", "--methods", "orb", "--work",
                            str(tmp_path / "work"), "--output", str(output)],
                           cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert child.returncode == 0, child.stderr[-3000:]
    [row] = json.loads(output.read_text())["rows"]
    assert (row["segment"], row["method"], row["poses"]) == ("5-25", "orb", 20)
    assert row["ate_sim3_cm"] <= row["ate_se3_cm"] + 1e-9 and row["ate_se3_cm"] < 3.0
    assert 0.9 < row["scale"] < 1.1


@pytest.mark.slow
def test_tracking_budget_splits_the_cpu_per_frame_and_runs_the_pipeline(synthetic_sequence_dir):
    from benchmarks.tracking_budget import budget, format_table, threaded_run

    row = budget(synthetic_sequence_dir, None, 12)
    stages = row["cpu_ms_per_frame"]
    assert set(stages) == {"reading", "extraction", "tracking", "mapping_thread"}
    assert all(value > 0 for value in stages.values())
    assert row["cpu_ms_per_frame_total"] == pytest.approx(sum(stages.values()))
    assert row["fps_bound"] == pytest.approx(row["cores"] * 1e3 / row["cpu_ms_per_frame_total"])
    # The inline budget run and the threaded CLI run both track the first 12 frames of the noise-free 160x120 loop.
    assert row["frames"] == 12 and row["ate_cm_inline"] < 2.0
    run = threaded_run(synthetic_sequence_dir, None, 12)
    assert run["fps_end_to_end"] > 0 and run["ate_cm"] < 2.0
    assert 0 < run["cores_busy"] <= row["cores"] + 0.5
    row["threaded_runs"] = [run]
    assert format_table(row).splitlines()[0].startswith("| reading ms |")


def test_camera_sweep_changes_only_the_focal_lengths_it_names(tmp_path):
    import dataclasses

    from benchmarks.camera_sweep import changed_camera_values
    from tambridge.camera import sensor_from_mapping

    camera_file = ROOT / "configs" / "cameras" / "7scenes_kinect.yaml"
    original = sensor_from_mapping(changed_camera_values(camera_file), camera_file)
    colour = sensor_from_mapping(changed_camera_values(camera_file, colour_focal_factor=1.024), camera_file)
    assert (colour.colour_camera.fx, colour.colour_camera.fy) == pytest.approx(
        (1.024 * original.colour_camera.fx, 1.024 * original.colour_camera.fy), rel=1e-12)
    assert dataclasses.replace(colour.colour_camera, fx=original.colour_camera.fx, fy=original.colour_camera.fy) \
        == original.colour_camera
    assert colour.camera == original.camera and (colour.depth_scale, colour.depth_invalid) == (1000.0, 65535)
    np.testing.assert_array_equal(colour.colour_from_depth, original.colour_from_depth)
    depth = sensor_from_mapping(changed_camera_values(camera_file, depth_fx=600.0), camera_file)
    assert (depth.camera.fx, depth.camera.fy) == (600.0, 600.0)
    assert dataclasses.replace(depth.camera, fx=585.0, fy=585.0) == original.camera
    assert depth.colour_camera == original.colour_camera
    registered = tmp_path / "registered.yaml"
    registered.write_text("width: 640\nheight: 480\nfx: 525\nfy: 525\ncx: 320\ncy: 240\n")
    with pytest.raises(SystemExit, match=r"registered\.yaml: has no colour camera"):
        changed_camera_values(registered, colour_focal_factor=1.1)


def test_sped_up_sequence_keeps_every_nth_frame_as_the_mean_of_its_exposure(synthetic_sequence_dir, tmp_path):
    """``benchmarks/sped_up_sequence.py``: every 4th colour frame from the first whose 3-frame window is whole, each
    the rounded mean of the 3 raw frames around it, under its own name and stamp; depth and ground truth linked."""
    import cv2
    import numpy as np

    from benchmarks.sped_up_sequence import write_sped_up
    from tambridge.errors import TambridgeError
    from tambridge.io.tum import open_sequence, read_file_list

    folder = tmp_path / "fast"
    folder.mkdir()
    assert write_sped_up(synthetic_sequence_dir, folder, 4, 3) == len(range(1, 29, 4))
    colour = read_file_list(synthetic_sequence_dir / "rgb.txt")
    assert read_file_list(folder / "rgb.txt") == [colour[i] for i in range(1, 29, 4)]
    stamp, name = colour[5]
    window = np.mean([cv2.imread(str(synthetic_sequence_dir / colour[j][1])).astype(np.float32) for j in (4, 5, 6)], axis=0)
    np.testing.assert_array_equal(cv2.imread(str(folder / name)), np.rint(window).astype(np.uint8))
    assert all((folder / name).is_symlink() for name in ("depth", "depth.txt", "groundtruth.txt", "camera.yaml"))
    sped_up, source = open_sequence(folder), open_sequence(synthetic_sequence_dir)
    assert len(sped_up) == 7
    np.testing.assert_array_equal(sped_up[1].depth_m, source[5].depth_m)

    short = tmp_path / "short"
    short.mkdir()
    (short / "rgb.txt").write_text("".join(f"{t:.6f} {n}\n" for t, n in colour[:2]))
    for _, n in colour[:2]:
        (short / n).parent.mkdir(exist_ok=True)
        (short / n).symlink_to(synthetic_sequence_dir / n)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(TambridgeError, match="fewer than one exposure of 3"):
        write_sped_up(short, empty, 4, 3)
    assert not any(empty.iterdir())


def test_smoothing_benchmark_refuses_a_smoothed_run_or_one_that_lost_frames(synthetic_sequence_dir, tmp_path):
    """``benchmarks/smoothing.py`` smooths a run's trajectory.txt: it refuses one smoothed already, and one that lost
    frames (it cannot split its smoothing there: the run folder only counts them), before it renders anything."""
    from benchmarks.smoothing import scores

    run_dir = tmp_path / "run"
    run_dir.mkdir()
    truth = (synthetic_sequence_dir / "groundtruth.txt").read_text()
    (run_dir / "trajectory.txt").write_text(truth)
    (run_dir / "keyframes.txt").write_text("".join(truth.splitlines(keepends=True)[:3]))
    (run_dir / "metrics.json").write_text(json.dumps({"frames_lost": 2}))
    (run_dir / "config.yaml").write_text("frontend:\n  smoothing:\n    enabled: true\n")
    with pytest.raises(SystemExit, match=r"run: its trajectory.txt is smoothed already"):
        scores(synthetic_sequence_dir, run_dir)
    (run_dir / "config.yaml").write_text("frontend:\n  smoothing:\n    enabled: false\n")
    with pytest.raises(SystemExit, match=r"run: 2 frames lost, and the run folder does not say which"):
        scores(synthetic_sequence_dir, run_dir)


def test_smoothing_benchmark_moves_the_ground_truth_into_the_run_by_poses_not_positions_alone():
    """On a straight path, positions leave a rotation about the path free; the fit by whole poses recovers the rigid
    transform between the ground truth and a run that is that transform of it, at every frame time inside the
    ground truth's span (interpolated)."""
    import numpy as np

    from benchmarks.smoothing import ground_truth_in_run
    from tambridge.geometry import exp_se3, exp_so3
    from tambridge.trajectory import Trajectory

    def path(times_s):
        """Along world x at 0.3 m/s, turning about the camera's y and z axes."""
        poses = np.tile(np.eye(4), (len(times_s), 1, 1))
        poses[:, :3, :3] = exp_so3(np.stack([np.zeros_like(times_s), 0.2 * np.sin(times_s), 0.1 * times_s], axis=1))
        poses[:, 0, 3] = 0.3 * times_s
        return poses

    stamps = np.arange(0.0, 3.0, 0.01)
    frame_stamps = np.arange(0.005, 3.0, 1 / 30)
    run_from_truth = exp_se3(np.array([0.5, -0.2, 1.0, 0.3, -1.2, 0.7]))
    frames = Trajectory(frame_stamps, run_from_truth @ path(frame_stamps))

    moved = ground_truth_in_run(Trajectory(stamps, path(stamps)), frames)

    inside = frame_stamps < stamps[-1]
    np.testing.assert_array_equal(moved.timestamps_s, frame_stamps[inside])
    # Interpolated 10 ms from a sample, the turning path is off by its curvature over that step only.
    np.testing.assert_allclose(moved.world_from_camera, frames.world_from_camera[inside], atol=1e-5)
