"""The benchmarks' sequence lookup (--data folders, a one-line message for a missing one), their row merging,
benchmarks/loops.py's ground-truth revisits and benchmarks/dense_tracking.py's longer exposures and lost-frame
diagnosis."""

import numpy as np
import pytest

from benchmarks.dense_tracking import longer_exposure, lost_frame_priors, lost_priors_summary, orb_config
from benchmarks.loops import relative_drift_m, revisits
from benchmarks.run_all import sequence_order
from benchmarks.sequences import FR1_XYZ, MissingSequence, find_sequence, merge_rows
from tambridge.geometry import exp_se3, inverse, rotation_angle_deg
from tambridge.io.tum import Frame, open_sequence


def _sequence(folder):
    folder.mkdir(parents=True)
    (folder / "rgb.txt").write_text("# none\n")
    return folder


def test_a_sequence_is_found_by_name_in_the_data_folders_or_by_path(tmp_path):
    first, second = tmp_path / "a", tmp_path / "b"
    found = _sequence(second / FR1_XYZ)
    assert find_sequence(FR1_XYZ, [first, second]) == found
    assert find_sequence(str(found), [first]) == found
    shadow = _sequence(first / FR1_XYZ)
    assert find_sequence(FR1_XYZ, [first, second]) == shadow  # the first folder wins


def test_a_missing_sequence_stops_with_one_line_naming_the_folders_and_how_to_get_it(tmp_path):
    with pytest.raises(MissingSequence) as raised:
        find_sequence(FR1_XYZ, [tmp_path / "x", tmp_path / "y"])
    message = str(raised.value)
    assert "\n" not in message and message.startswith(f"{FR1_XYZ}: not found in {tmp_path / 'x'}, {tmp_path / 'y'}")
    assert "tambridge download fr1/xyz" in message and "neha191091/3d_scan_exercises" in message and "0229f5f" in message
    with pytest.raises(MissingSequence, match=r"^other: not found in .*--data$"):
        find_sequence("other", [tmp_path])


def test_rows_of_a_subset_run_replace_their_own_and_keep_the_rest():
    old = [{"sequence": "s", "method": "m", "ate": 1}, {"sequence": "t", "method": "m", "ate": 2}]
    new = [{"sequence": "t", "method": "m", "ate": 3}, {"sequence": "u", "method": "m", "ate": 4}]
    merged = merge_rows(old, new, ("sequence", "method"))
    assert [(row["sequence"], row["ate"]) for row in merged] == [("s", 1), ("t", 3), ("u", 4)]
    rows = [{"sequence": "7scenes", "method": "tambridge fast"}, {"sequence": FR1_XYZ, "method": "tambridge fast"},
            {"sequence": FR1_XYZ, "method": "tambridge default"}]
    assert sorted(rows, key=sequence_order) == [rows[2], rows[1], rows[0]]


def test_revisits_are_pairs_far_apart_in_time_near_in_pose():
    times = np.arange(6, dtype=float)
    # Twists are (translation, rotation): a camera moving 8 mm a second along x, then back near the start.
    poses = np.stack([exp_se3(np.array([0.008 * i, 0.0, 0.0, 0.0, 0.0, 0.0])) for i in range(6)])
    poses[5] = exp_se3(np.array([0.001, 0.0, 0.0, 0.0, 0.0, 0.0]))  # back at the start
    poses[4] = exp_se3(np.array([0.0, 0.0, 0.0, 0.0, np.deg2rad(30.0), 0.0]))  # at the start, looking aside
    assert revisits(times, poses, min_gap_s=3.0, within_m=0.01, within_deg=10.0) == [(5, 0), (5, 1)]
    assert revisits(times, poses, min_gap_s=4.5, within_m=0.01, within_deg=10.0) == [(5, 0)]
    # Drift between a revisit's ends: the estimate's relative translation against the truth's.
    estimate = poses.copy()
    estimate[5, 0, 3] += 0.03
    assert relative_drift_m(estimate, poses, 5, 0) == pytest.approx(0.03)


def test_a_longer_exposure_is_the_mean_of_the_frames_around_one_with_its_own_depth_and_stamps():
    frames = [Frame(index, 0.1 * index, np.full((2, 3, 3), 10 * index, np.uint8),
                    np.full((2, 3), 1.0 + index, np.float32), 0.1 * index + 0.01) for index in range(5)]
    frames[2].rgb[0, 0] = (21, 0, 255)
    blurred = longer_exposure(frames, 2, 3)
    expected = np.full((2, 3, 3), 20, np.uint8)
    expected[0, 0] = (20, 13, 98)  # (10 + 21 + 30) / 3, (10 + 0 + 30) / 3 and (10 + 255 + 30) / 3, rounded
    np.testing.assert_array_equal(blurred.rgb, expected)
    assert (blurred.index, blurred.timestamp_s, blurred.depth_delay_s) == (2, frames[2].timestamp_s, frames[2].depth_delay_s)
    assert blurred.depth_m is frames[2].depth_m
    # At the ends the window is cut: frame 0 takes frames 0 and 1.
    np.testing.assert_array_equal(longer_exposure(frames, 0, 3).rgb, np.full((2, 3, 3), 5, np.uint8))
    assert longer_exposure(frames, 4, 1) is frames[4]


def test_lost_frames_of_a_fast_camera_are_placed_from_the_ground_truth_pose(synthetic_sequence_dir):
    """dense_tracking.py --lost-priors on every 4th frame of the synthetic loop, from the second: tracking loses
    frames whose prior is far off; searched from the ground-truth pose (put into the run's world through the first
    tracked frame) the same local map places them near the truth, so the image was not the cause."""
    sequence = open_sequence(synthetic_sequence_dir)
    frames = [sequence[index] for index in range(1, len(sequence), 4)]
    diagnosis = lost_frame_priors(frames, sequence, orb_config([]))
    lost = diagnosis["lost"]
    assert len(lost) >= 2 and all(row["prior_error_cm"] > 10.0 for row in lost)
    placed = [row["from_ground_truth"] for row in lost if row["from_ground_truth"]["inliers"] >= 30]
    assert placed and all(fix["error_cm"] < 3.0 for fix in placed)
    assert all(row["final_error_cm"] > 5.0 for row in lost) and diagnosis["lost_frames_over_5cm"] == len(lost)
    # The first lost frame follows the one tracked frame, which leaves no velocity: its prior is that frame's pose, so
    # the prior is off by the whole step the camera took between them (frames 1 and 5 of the loop).
    truth = sequence.ground_truth.world_from_camera
    step = inverse(truth[1]) @ truth[5]
    assert (lost[0]["position"], lost[0]["after"]) == (1, "tracked")
    assert lost[0]["prior_error_cm"] == pytest.approx(100 * np.linalg.norm(step[:3, 3]), abs=0.5)
    assert lost[0]["prior_error_deg"] == pytest.approx(rotation_angle_deg(step), abs=0.5)


def test_the_lost_priors_summary_counts_placed_frames_and_those_near_the_truth():
    diagnosis = {"frames_over_5cm": 3, "lost_frames_over_5cm": 2, "lost": [
        {"prior_error_cm": 10.0, "from_ground_truth": {"inliers": 40, "error_cm": 1.0},
         "from_prior_radius_x4": {"inliers": 35, "error_cm": 22.5}},
        {"prior_error_cm": 30.0, "from_ground_truth": {"inliers": 29, "error_cm": 0.5},
         "from_prior_radius_x4": {"inliers": 0, "error_cm": None}}]}
    assert lost_priors_summary(diagnosis, 30) == (
        "2 lost frames; their priors 20.0 cm off (median); from_ground_truth: 1 placed, 1 within 5 cm, worst 1.00 cm; "
        "from_prior_radius_x4: 1 placed, 0 within 5 cm, worst 22.50 cm; 3 frames over 5 cm in the run, 2 of them lost")
    assert lost_priors_summary({"frames_over_5cm": 0, "lost_frames_over_5cm": 0, "lost": []}, 30) == (
        "no lost frames; 0 frames over 5 cm in the run")
