"""The worst segment of a trajectory: error injected into a known span of a synthetic path is found there, and
the report names it."""

import numpy as np
import pytest

from tambridge.evaluation.metrics import DeviceMetrics, RunMetrics
from tambridge.evaluation.report import write_report
from tambridge.evaluation.trajectory import evaluate_trajectory, worst_error_window
from tambridge.io.synthetic import loop_path
from tambridge.trajectory import Trajectory

FPS = 30.0
BAD = slice(240, 270)  # frames 240-269, 8.0-9.0 s: the injected segment


def _with_injected_error(count: int = 600) -> tuple[Trajectory, Trajectory]:
    """A 20-s loop and an estimate with 1 mm noise everywhere and 3 cm more in frames ``BAD``."""
    reference = Trajectory(np.arange(count) / FPS, loop_path(count))
    rng = np.random.default_rng(7)
    offsets = rng.normal(0.0, 0.001, (count, 3))
    directions = rng.normal(size=(BAD.stop - BAD.start, 3))
    offsets[BAD] += 0.03 * directions / np.linalg.norm(directions, axis=1, keepdims=True)
    estimate = reference.world_from_camera.copy()
    estimate[:, :3, 3] += offsets
    return Trajectory(reference.timestamps_s.copy(), estimate), reference


def _brute_force(timestamps_s, errors_m, window_s):
    """Every window that starts at a pose and spans window_s (or the whole path when shorter), RMSE by the sum;
    times within a microsecond count as equal."""
    best, reach_s = None, window_s + 1e-6
    for first in range(len(timestamps_s)):
        if timestamps_s[-1] - timestamps_s[0] >= window_s and timestamps_s[-1] - timestamps_s[first] < window_s - 1e-6:
            break
        inside = [i for i in range(first, len(timestamps_s)) if timestamps_s[i] - timestamps_s[first] <= reach_s]
        rmse = np.sqrt(np.mean(errors_m[inside] ** 2))
        if best is None or rmse > best[2]:
            best = (first, inside[-1], rmse)
        if timestamps_s[-1] - timestamps_s[0] < window_s:
            break
    return best


def test_the_worst_window_holds_the_injected_segment():
    estimate, reference = _with_injected_error()
    errors = evaluate_trajectory(estimate, reference, "se3")
    worst = worst_error_window(errors.timestamps_s, errors.ate_errors_m, window_s=2.0)
    # The 2-s window (61 poses) covers the whole 1-s segment, and its RMSE is the segment's diluted by the rest.
    assert worst.first <= BAD.start and worst.last >= BAD.stop - 1
    assert worst.last - worst.first == 60
    assert worst.end_s - worst.start_s == pytest.approx(2.0)
    assert worst.start_s == pytest.approx(errors.timestamps_s[worst.first])
    expected = np.sqrt(30 * 0.03**2 / 61)
    assert worst.rmse_m == pytest.approx(expected, rel=0.1)
    assert errors.ate_rmse_m < 0.6 * worst.rmse_m
    first, last, rmse = _brute_force(errors.timestamps_s, errors.ate_errors_m, 2.0)
    assert (worst.first, worst.last) == (first, last) and worst.rmse_m == pytest.approx(rmse, rel=1e-9)
    # A window of the segment's own length finds exactly the segment.
    exact = worst_error_window(errors.timestamps_s, errors.ate_errors_m, window_s=29 / FPS)
    assert (exact.first, exact.last) == (BAD.start, BAD.stop - 1)
    assert exact.rmse_m == pytest.approx(0.03, rel=0.1)


def test_a_path_shorter_than_the_window_is_one_window_and_bad_input_is_refused():
    times = np.arange(10) / FPS
    errors = np.linspace(0.0, 0.01, 10)
    worst = worst_error_window(times, errors, window_s=2.0)
    assert (worst.first, worst.last) == (0, 9)
    assert worst.rmse_m == pytest.approx(np.sqrt(np.mean(errors**2)))
    rng = np.random.default_rng(1)
    uneven = np.cumsum(rng.uniform(0.01, 0.2, 80))
    values = rng.uniform(0, 1, 80)
    found = worst_error_window(uneven, values, 1.0)
    assert (found.first, found.last) == _brute_force(uneven, values, 1.0)[:2]
    with pytest.raises(ValueError, match="3 timestamps for 2 errors"):
        worst_error_window(np.zeros(3), np.zeros(2))


def test_the_report_names_the_worst_segment(tmp_path):
    estimate, reference = _with_injected_error()
    errors = evaluate_trajectory(estimate, reference, "se3")
    metrics = RunMetrics(
        sequence="seq", frames=600, keyframes=5, frontend="orb", frames_lost=0, frames_relocalised=0,
        frames_without_depth=0, loops_closed=0, keyframes_culled=0, frontend_seconds_per_stage={}, seconds_total=10.0,
        fps_end_to_end=3.0, seconds_per_stage={}, fps_per_stage={}, peak_memory_mb=500.0,
        peak_memory_mb_tracking=400.0, warnings=0, trajectory=None, trajectory_unavailable="test",
        device=DeviceMetrics(device="cpu"))
    index = write_report(tmp_path / "report", metrics, {"tambridge (SE(3))": errors})
    worst = worst_error_window(errors.timestamps_s, errors.ate_errors_m)
    page = index.read_text()
    assert "Worst 2-second segment" in page
    assert f"poses {worst.first}-{worst.last}, {worst.start_s:.1f}-{worst.end_s:.1f} s" in page
    assert f"RMSE {worst.rmse_m * 100:.2f} cm" in page
    assert (tmp_path / "report" / "trajectory.png").stat().st_size > 10_000
