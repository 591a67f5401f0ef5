"""``tambridge colmap``: COLMAP on every n-th colour image of a sequence, its trajectory and its Sim(3) error.

Outputs in ``output_dir``: ``trajectory.txt`` (TUM, registered images only, marked monocular so ``tambridge
compare`` aligns it with Sim(3)), ``trajectory.png`` and ``metrics.json`` (with ATE/RPE when the sequence has
ground truth). ``metrics.json`` is written last.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path

from tambridge.errors import TambridgeError, TrajectoryEvaluationError
from tambridge.evaluation.colmap import ColmapOptions, run_colmap, write_monocular_trajectory
from tambridge.evaluation.plots import plot_trajectory_errors
from tambridge.evaluation.trajectory import TrajectoryErrors, evaluate_trajectory
from tambridge.files import atomic_write_text, check_output_file
from tambridge.io.tum import open_sequence
from tambridge.trajectory import Trajectory

logger = logging.getLogger("tambridge.pipelines.colmap")

OUTPUT_FILES = ("trajectory.txt", "trajectory.png", "metrics.json")


@dataclasses.dataclass
class ColmapRun:
    """COLMAP's trajectory (registered images), its errors against ground truth (None without), the metrics."""

    trajectory: Trajectory
    errors: TrajectoryErrors | None
    metrics: dict
    output_dir: Path


def colmap(
    sequence_dir: Path,
    output_dir: Path,
    every: int = 5,
    max_frames: int | None = None,
    camera_file: Path | None = None,
    options: ColmapOptions = ColmapOptions(),
) -> ColmapRun:
    """Run COLMAP on every ``every``-th frame of ``sequence_dir`` (at most ``max_frames`` of them) into ``output_dir``
    (new, or one this command wrote before). Ground truth on another clock leaves the trajectory without errors
    (metrics.json ``trajectory_unavailable`` says why), as ``tambridge reconstruct`` does."""
    output_dir = Path(output_dir)
    sequence = open_sequence(sequence_dir, camera_file=camera_file, stride=every, max_frames=max_frames)
    for name in OUTPUT_FILES:
        check_output_file(output_dir / name, "-o")
    others = sorted(set(path.name for path in output_dir.iterdir()) - set(OUTPUT_FILES)) if output_dir.is_dir() else []
    if others:
        raise TambridgeError(f"-o {output_dir}: holds files this command did not write ({', '.join(others[:3])}); give "
                             "a new folder or one of an earlier tambridge colmap")
    started = time.perf_counter()
    result = run_colmap((frame.rgb for frame in sequence), sequence.timestamps_s, sequence.camera, options)
    seconds = time.perf_counter() - started
    # An earlier result stays whole until COLMAP has given a new one; metrics.json, written last, marks it whole.
    output_dir.mkdir(parents=True, exist_ok=True)
    (output_dir / "metrics.json").unlink(missing_ok=True)
    (output_dir / "trajectory.png").unlink(missing_ok=True)
    write_monocular_trajectory(output_dir / "trajectory.txt", result.trajectory)
    metrics = {
        "sequence": str(sequence_dir),
        "every": every,
        "images": result.image_count,
        "registered": result.registered_count,
        "points": len(result.points_world),
        "seconds": seconds,
        "trajectory": None,
    }
    errors = None
    if sequence.ground_truth is not None:
        try:
            errors = evaluate_trajectory(result.trajectory, sequence.ground_truth, align="sim3")
        except TrajectoryEvaluationError as error:
            metrics["trajectory_unavailable"] = str(error)
            logger.warning("no ATE for COLMAP's trajectory: %s", error)
    if errors is not None:
        metrics["trajectory"] = errors.summary()
        plot_trajectory_errors({"COLMAP (Sim(3))": errors}, output_dir / "trajectory.png", title=str(sequence_dir))
        logger.info("COLMAP ATE RMSE %.2f cm over %d poses (Sim(3)-aligned)", errors.ate_rmse_m * 100, errors.pose_count)
    atomic_write_text(output_dir / "metrics.json", json.dumps(metrics, indent=2) + "\n")
    return ColmapRun(result.trajectory, errors, metrics, output_dir)
