"""benchmarks/reference_agreement.py: two estimates that miss the reference the same way agree with each other."""

import numpy as np
import pytest

from benchmarks.reference_agreement import agreement
from tambridge.geometry import exp_se3
from tambridge.io.synthetic import loop_path
from tambridge.trajectory import Trajectory


def _offset(trajectory: Trajectory, offsets_m: np.ndarray) -> Trajectory:
    moved = trajectory.world_from_camera.copy()
    moved[:, :3, 3] += offsets_m
    return Trajectory(trajectory.timestamps_s, moved)


def test_estimates_sharing_an_error_agree_and_correlate_while_an_unrelated_one_does_not():
    count = 80
    truth = Trajectory(np.arange(count) / 30.0, loop_path(count))
    rng = np.random.default_rng(5)
    shared = rng.normal(0.0, 0.03, size=(count, 3))
    shared -= shared.mean(axis=0)
    own = rng.normal(0.0, 0.002, size=(count, 3))
    tracker = _offset(truth, shared + own)
    # A monocular estimate: the same error in another frame and at a fifth of the scale.
    similar = _offset(truth, shared).world_from_camera.copy()
    similar[:, :3, 3] *= 0.2
    colmap = Trajectory(truth.timestamps_s, exp_se3(np.array([0.5, -1.0, 0.2, 0.1, 0.3, -0.2])) @ similar)
    unrelated = _offset(truth, rng.normal(0.0, 0.03, size=(count, 3)))

    result = agreement({"tracker": tracker, "COLMAP": colmap, "other": unrelated}, truth)

    expected_to_truth_cm = 100.0 * np.sqrt(np.mean(np.sum(shared**2, axis=1)))
    assert result["ate_cm"]["COLMAP"]["ground truth"] == pytest.approx(expected_to_truth_cm, rel=0.1)
    # The pair is scored in metres either way round: COLMAP is the one scaled.
    assert result["ate_cm"]["tracker"]["COLMAP"] == pytest.approx(result["ate_cm"]["COLMAP"]["tracker"], rel=0.05)
    assert result["ate_cm"]["tracker"]["COLMAP"] < 0.5 < expected_to_truth_cm / 4
    assert result["ate_cm"]["other"]["tracker"] > expected_to_truth_cm
    assert result["error_correlation"]["tracker"]["COLMAP"] > 0.99
    assert abs(result["error_correlation"]["tracker"]["other"]) < 0.3
