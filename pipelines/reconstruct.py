"""``tambridge reconstruct``: sequence -> frontend -> (bridge -> mapper) -> exporters -> evaluation.

Every output is written atomically; ``metrics.json`` is written last, so its presence says the run finished.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path
from typing import Callable

from tqdm import tqdm

from tambridge.camera import Camera
from tambridge.config import Config, ConfigError, to_yaml
from tambridge.evaluation.trajectory import evaluate_trajectory
from tambridge.export.atomic import atomic_write_text
from tambridge.frontend.open3d_odometry import FrameToFrameOdometry
from tambridge.frontend.types import Frontend, FrontendResult, TrackResult
from tambridge.io.tum import Frame, RgbdSequence, open_sequence
from tambridge.runlog import RunLog, peak_memory_mb
from tambridge.trajectory import Trajectory, write_tum_trajectory

from pipelines.mapping import MappingStage, mapping_metrics

logger = logging.getLogger("tambridge.pipelines.reconstruct")


@dataclasses.dataclass
class ReconstructResult:
    """What a run produced: the per-frame trajectory, the metrics written to metrics.json, the output folder."""

    trajectory: Trajectory
    keyframes: Trajectory
    metrics: dict
    output_dir: Path


def make_frontend(config: Config, camera: Camera) -> Frontend:
    """The frontend named by ``config.frontend.kind``."""
    kind = config.frontend.kind
    if kind == "open3d_f2f":
        return FrameToFrameOdometry(camera, config.frontend.odometry_max_depth_m, config.frontend.odometry_depth_diff_max_m)
    raise ConfigError(f"frontend.kind={kind!r}: expected one of open3d_f2f")


def track_sequence(
    sequence: RgbdSequence,
    frontend: Frontend,
    run_log: RunLog,
    progress: bool,
    on_keyframe: Callable[[TrackResult, Frame], None] | None = None,
) -> FrontendResult:
    """Feed every frame to the frontend in order; returns its final result (after loop closure and global BA).

    ``on_keyframe(result, frame)`` is called after each frame that made a keyframe (the online mapping); its time
    is not counted as tracking.
    """
    for frame in tqdm(sequence, total=len(sequence), desc="tracking", unit="frame", disable=not progress):
        with run_log.stage("tracking"):
            result = frontend.track(frame)
        if on_keyframe is not None and result.keyframe is not None:
            on_keyframe(result, frame)
    with run_log.stage("tracking"):
        return frontend.finish()


def reconstruct(sequence_dir: Path, output_dir: Path, config: Config, progress: bool = True) -> ReconstructResult:
    """Reconstruct a TUM-layout sequence into ``output_dir`` (see DESIGN.md for the folder's contents)."""
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    for stale in ("metrics.json", "trajectory.txt", "keyframes.txt", "splats.ply"):
        # A re-run into the same folder must not leave an earlier run's results looking like this run's.
        (output_dir / stale).unlink(missing_ok=True)
    run_log = RunLog(output_dir / "run.log")
    started = time.perf_counter()
    try:
        atomic_write_text(output_dir / "config.yaml", to_yaml(config))
        logger.info("reconstructing %s into %s", sequence_dir, output_dir)
        with run_log.stage("read"):
            sequence = open_sequence(
                sequence_dir,
                camera_file=None if config.input.camera_file is None else Path(config.input.camera_file),
                stride=config.input.stride,
                max_frames=config.input.max_frames,
            )
        logger.info("%d frames, camera %s", len(sequence), sequence.camera)
        frontend = make_frontend(config, sequence.camera)
        mapping = MappingStage(sequence, config, run_log) if config.mapper.enabled else None
        on_keyframe = None
        if mapping is not None:
            on_keyframe = lambda result, frame: mapping.on_keyframe(result.keyframe, frame, frontend.keyframe_poses())  # noqa: E731
        tracking = track_sequence(sequence, frontend, run_log, progress, on_keyframe)
        trajectory, keyframes = tracking.trajectory, tracking.keyframe_trajectory
        write_tum_trajectory(output_dir / "trajectory.txt", trajectory)
        write_tum_trajectory(output_dir / "keyframes.txt", keyframes)
        if mapping is not None:
            mapping.finish(tracking.keyframe_poses, output_dir / "splats.ply")
        # End to end = what a user waits for to get trajectory and map; the rendering evaluation below is not part of it.
        total_s = time.perf_counter() - started
        metrics = {
            "sequence": str(sequence_dir),
            "frames": len(sequence),
            "keyframes": len(keyframes),
            "frontend": config.frontend.kind,
            "frames_lost": tracking.frames_lost,
            "frames_relocalised": tracking.frames_relocalised,
            "loops_closed": tracking.loops_closed,
            "frontend_seconds_per_stage": tracking.timings_s,
            "seconds_total": total_s,
            "fps_end_to_end": len(sequence) / total_s,
            "seconds_per_stage": dict(run_log.stage_seconds),
            "fps_per_stage": {name: len(sequence) / max(s, 1e-9) for name, s in run_log.stage_seconds.items()},
            "peak_memory_mb": peak_memory_mb(),
            "warnings": run_log.warnings,
            "trajectory": None,
        }
        if mapping is not None:
            metrics.update(mapping_metrics(mapping, tracking, sequence, config, run_log))
            # The evaluation ran after the figures above were taken: refresh what it adds to.
            metrics.update(seconds_per_stage=dict(run_log.stage_seconds), peak_memory_mb=peak_memory_mb(),
                           warnings=run_log.warnings)
        if sequence.ground_truth is not None:
            errors = evaluate_trajectory(trajectory, sequence.ground_truth, align="se3")
            metrics["trajectory"] = errors.summary()
            logger.info("ATE RMSE %.2f cm over %d poses (SE(3)-aligned)", errors.ate_rmse_m * 100, errors.pose_count)
        atomic_write_text(output_dir / "metrics.json", json.dumps(metrics, indent=2) + "\n")
        logger.info("finished in %.1f s", total_s)
        return ReconstructResult(trajectory, keyframes, metrics, output_dir)
    except BaseException as error:
        run_log.record_stop(error)
        raise
    finally:
        run_log.close()
