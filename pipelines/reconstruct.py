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

import numpy as np
from tqdm import tqdm

from tambridge.camera import Camera
from tambridge.checkpoint import (
    Checkpoint,
    KeyframeCheckpoints,
    check_resumable,
    checkpoint_path,
    load_checkpoint,
    sequence_fingerprint,
)
from tambridge.config import Config, to_dict, to_yaml
from tambridge.errors import ConfigError
from tambridge.device import device_summary, resolve_device
from tambridge.evaluation.report import RenderPair, write_report
from tambridge.evaluation.trajectory import TrajectoryErrors, evaluate_trajectory
from tambridge.files import atomic_write_text
from tambridge.evaluation.mapping import mapping_metrics
from tambridge.export.mesh import fuse_tsdf_mesh, gaussian_views, sensor_views, write_mesh
from tambridge.export.splats import save_ply
from tambridge.frontend.open3d.frontend import Open3dFrontend
from tambridge.frontend.open3d.odometry import FrameToFrameOdometry
from tambridge.frontend.orb.frontend import OrbFrontend
from tambridge.frontend.contract import Frontend, FrontendResult, TrackResult
from tambridge.io.prefetch import FramePrefetcher
from tambridge.io.tum import Frame, RgbdSequence, open_sequence
from tambridge.runlog import RunLog, peak_memory_mb
from tambridge.trajectory import Trajectory, read_tum_trajectory, write_tum_trajectory
from tambridge.viewer import RerunViewer

from tambridge.mapping.stage import MappingStage

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
    settings = config.frontend
    if settings.kind == "orb":
        return OrbFrontend(camera, settings.orb)
    if settings.kind == "open3d":
        return Open3dFrontend(camera, settings.open3d)
    if settings.kind == "open3d_f2f":
        return FrameToFrameOdometry(camera, settings.open3d.max_depth_m, settings.open3d.depth_diff_max_m)
    raise ConfigError(f"frontend.kind={settings.kind!r}: expected one of orb, open3d, open3d_f2f")


def track_sequence(
    sequence: RgbdSequence,
    frontend: Frontend,
    run_log: RunLog,
    progress: bool,
    on_keyframe: Callable[[TrackResult, Frame], None] | None = None,
    on_frame: Callable[[TrackResult, Frame], None] | None = None,
    start_frame: int = 0,
    checkpoints: KeyframeCheckpoints | None = None,
    prefetch: bool = True,
) -> FrontendResult:
    """Feed every frame from ``start_frame`` on to the frontend in order; returns its final result (after loop
    closure and global BA).

    ``on_keyframe(result, frame)`` is called after each frame that made a keyframe (the online mapping); its time
    is not counted as tracking. ``on_frame(result, frame)`` is called after every frame (the live view, the
    mapper's coverage check).
    ``checkpoints`` is told of every keyframe once the frame is mapped (``start_frame > 0``: a resumed run).
    ``prefetch``: frame i+2 is read in one worker thread and frame i+1's ORB features are extracted in another
    while frame i is tracked (:class:`FramePrefetcher`), with the results of reading and tracking one frame after the
    other. Stage "frame_reading" is the time spent waiting for the next frame (reading it, or with ``prefetch``
    what its reading and extraction did not hide behind tracking); "tracking" is the rest of the frontend's time.
    """
    # Feature extraction is the one per-frame step of tracking that needs nothing from earlier frames.
    extract = frontend.extract if prefetch and isinstance(frontend, OrbFrontend) else None
    with FramePrefetcher(sequence, start_frame, extract, read_ahead=prefetch) as prefetcher:
        frames = iter(prefetcher)
        for index in tqdm(range(start_frame, len(sequence)), total=len(sequence), initial=start_frame,
                          desc="tracking", unit="frame", disable=not progress):
            with run_log.stage("frame_reading"):
                frame, features = next(frames)
            with run_log.stage("tracking"):
                result = frontend.track(frame) if extract is None else frontend.track(frame, features)
            if on_keyframe is not None and result.keyframe is not None:
                on_keyframe(result, frame)
            if on_frame is not None:
                on_frame(result, frame)
            if checkpoints is not None and result.is_keyframe:
                with run_log.stage("checkpoint"):
                    checkpoints.after_keyframe(index + 1)
    with run_log.stage("tracking"):
        return frontend.finish()


def reconstruct(
    sequence_dir: Path, output_dir: Path, config: Config, progress: bool = True, viewer: str | None = None,
    resume: bool = False,
) -> ReconstructResult:
    """Reconstruct a TUM-layout sequence into ``output_dir`` (see DESIGN.md for the folder's contents).

    ``viewer``: ``"rerun"`` streams the run to a spawned rerun viewer, ``"rerun:FILE.rrd"`` saves a recording.
    ``resume``: continue from ``output_dir/checkpoint/`` (written every ``checkpoint.every_keyframes`` keyframes by
    a run with the same config and sequence); the result is that of an uninterrupted run.
    """
    # Before anything is read or removed: a run asked to use a GPU it cannot have stops here.
    device = resolve_device(config.device)
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    checkpoint_file = checkpoint_path(output_dir)
    stale_outputs = ["metrics.json", "trajectory.txt", "keyframes.txt", "splats.ply", "mesh.ply", "report/index.html"]
    if resume:
        # Before anything is removed: --resume on a finished run (no checkpoint) must not cost its results.
        checkpoint = load_checkpoint(checkpoint_file)
    else:
        stale_outputs.append(str(checkpoint_file.relative_to(output_dir)))
    for stale in stale_outputs:
        # A re-run into the same folder must not leave an earlier run's results looking like this run's.
        (output_dir / stale).unlink(missing_ok=True)
    run_log = RunLog(output_dir / "run.log", append=resume)
    started = time.perf_counter()
    live_view = None
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
        mapping = MappingStage(sequence, config, run_log, device) if config.mapper.enabled else None
        logger.info("Gaussian map, bridge and rendering evaluation on %s", device if mapping is not None else "(mapper off)")
        on_keyframe = None
        if mapping is not None:
            on_keyframe = lambda result, frame: mapping.on_keyframe(result.keyframe, frame, frontend.keyframe_poses())  # noqa: E731
        live_view = RerunViewer(viewer, sequence.camera) if viewer else None
        gaussian_counts: list[tuple[int, int]] = []
        frames_without_depth: list[int] = []
        fingerprint = sequence_fingerprint(sequence.folder, sequence.timestamps_s, sequence.sensor)
        start_frame, keyframes_so_far = 0, 0
        if resume:
            check_resumable(checkpoint_file, checkpoint, to_dict(config), fingerprint)
            start_frame, keyframes_so_far, elapsed_s = restore_run(checkpoint, frontend, mapping, run_log, gaussian_counts,
                                                                   frames_without_depth)
            started -= elapsed_s
            logger.info("resuming from %s at frame %d of %d (%d keyframes)", checkpoint_file, start_frame,
                        len(sequence), keyframes_so_far)
        checkpoints = None
        if config.checkpoint.every_keyframes:

            def snapshot(next_frame: int) -> Checkpoint:
                run = {"stage_seconds": dict(run_log.stage_seconds), "warnings": run_log.warnings,
                       "elapsed_s": time.perf_counter() - started, "gaussian_counts": list(gaussian_counts),
                       "frames_without_depth": list(frames_without_depth), "keyframes": checkpoints.keyframes}
                return Checkpoint(next_frame, to_dict(config), fingerprint, frontend.state_dict(),
                                  None if mapping is None else mapping.state_dict(), run)

            checkpoints = KeyframeCheckpoints(checkpoint_file, config.checkpoint.every_keyframes, snapshot, keyframes_so_far)

        def on_frame(result: TrackResult, frame: Frame) -> None:
            if not (frame.depth_m > 0).any():
                # A frame without depth still tracks from colour (PnP on the map) but adds nothing to either map.
                frames_without_depth.append(frame.index)
                logger.warning("frame %d (t=%.6f): no valid depth in %s; %s", frame.index, frame.timestamp_s,
                               sequence.depth_paths[frame.index].name,
                               "tracked from colour" if result.tracked else "not tracked")
            if mapping is not None:
                gaussian_counts.append((frame.index, len(mapping.map)))
                if mapping.needs_view(result, frame):
                    frontend.request_keyframe()
            if live_view is not None:
                with run_log.stage("viewer"):
                    live_view.log_frame(frame.index, frame.timestamp_s, result.world_from_camera, frame.rgb,
                                        frame.depth_m, result.is_keyframe)

        tracking = track_sequence(sequence, frontend, run_log, progress, on_keyframe, on_frame, start_frame, checkpoints,
                                  config.frontend.prefetch)
        # The peak of the online part (tracking and mapping every frame); exports and evaluation come after it.
        peak_memory_tracking_mb = peak_memory_mb()
        trajectory, keyframes = tracking.trajectory, tracking.keyframe_trajectory
        write_tum_trajectory(output_dir / "trajectory.txt", trajectory)
        write_tum_trajectory(output_dir / "keyframes.txt", keyframes)
        if mapping is not None:
            mapping.finish(tracking.keyframe_poses)
            with run_log.stage("export"):
                save_ply(output_dir / "splats.ply", mapping.map.world_gaussians())
        if config.mesh.enabled:
            with run_log.stage("mesh"):
                write_run_mesh(output_dir / "mesh.ply", sequence, trajectory, config, mapping)
        if live_view is not None:
            with run_log.stage("viewer"):
                log_final_state(live_view, sequence, tracking, mapping)
        # End to end = what a user waits for to get trajectory and map; the rendering evaluation below is not part of it.
        total_s = time.perf_counter() - started
        metrics = {
            "sequence": str(sequence_dir),
            "frames": len(sequence),
            "keyframes": len(keyframes),
            "frontend": config.frontend.kind,
            "frames_lost": tracking.frames_lost,
            "frames_relocalised": tracking.frames_relocalised,
            "frames_without_depth": len(frames_without_depth),
            "loops_closed": tracking.loops_closed,
            "keyframes_culled": tracking.keyframes_culled,
            "frontend_seconds_per_stage": tracking.timings_s,
            "seconds_total": total_s,
            "fps_end_to_end": len(sequence) / total_s,
            "seconds_per_stage": dict(run_log.stage_seconds),
            "fps_per_stage": {name: len(sequence) / max(s, 1e-9) for name, s in run_log.stage_seconds.items()},
            "peak_memory_mb": peak_memory_mb(),
            "peak_memory_mb_tracking": peak_memory_tracking_mb,
            "warnings": run_log.warnings,
            "trajectory": None,
        }
        if mapping is not None:
            metrics.update(mapping_metrics(mapping, tracking, sequence, config, run_log))
            # The evaluation ran after the figures above were taken: refresh what it adds to.
            metrics.update(seconds_per_stage=dict(run_log.stage_seconds), peak_memory_mb=peak_memory_mb(),
                           warnings=run_log.warnings)
        # The frontend, the mesh and the exporters run on the CPU: the device is the mapping stage's.
        metrics.update(device_summary(device) if mapping is not None else {"device": "cpu"})
        errors = None
        if sequence.ground_truth is not None:
            errors = evaluate_trajectory(trajectory, sequence.ground_truth, align="se3")
            metrics["trajectory"] = errors.summary()
            logger.info("ATE RMSE %.2f cm over %d poses (SE(3)-aligned)", errors.ate_rmse_m * 100, errors.pose_count)
        write_run_report(output_dir, metrics, sequence, errors, mapping, trajectory, gaussian_counts)
        atomic_write_text(output_dir / "metrics.json", json.dumps(metrics, indent=2) + "\n")
        # The run is whole: nothing is left to resume.
        checkpoint_file.unlink(missing_ok=True)
        logger.info("finished in %.1f s", total_s)
        return ReconstructResult(trajectory, keyframes, metrics, output_dir)
    except BaseException as error:
        run_log.record_stop(error)
        raise
    finally:
        if live_view is not None:
            live_view.close()
        run_log.close()


def restore_run(checkpoint: Checkpoint, frontend: Frontend, mapping: MappingStage | None, run_log: RunLog,
                gaussian_counts: list[tuple[int, int]], frames_without_depth: list[int]) -> tuple[int, int, float]:
    """Load a checkpoint's state into a fresh frontend and mapping stage, and its counters into ``run_log``,
    ``gaussian_counts`` and ``frames_without_depth``; returns (next frame, keyframes so far, seconds the run had
    taken)."""
    frontend.load_state_dict(checkpoint.frontend)
    if mapping is not None:
        mapping.load_state_dict(checkpoint.mapping)
    run = checkpoint.run
    for stage, seconds in run["stage_seconds"].items():
        run_log.stage_seconds[stage] = run_log.stage_seconds.get(stage, 0.0) + seconds
    run_log.warnings += run["warnings"]
    gaussian_counts.extend(run["gaussian_counts"])
    frames_without_depth.extend(run["frames_without_depth"])
    return checkpoint.next_frame, run["keyframes"], run["elapsed_s"]


REPORT_RENDERS = 4
"""Frames rendered from the map for the report's grid (at the mapping resolution: cheap)."""


def write_run_mesh(path: Path, sequence: RgbdSequence, trajectory: Trajectory, config: Config,
                   mapping: MappingStage | None) -> None:
    """TSDF mesh of every ``mesh.frame_stride``-th frame at its final pose; ``mesh.source=gaussians`` fuses the
    map's rendered depth (at the mapping resolution, from the rendering poses) instead of the sensor's."""
    source = config.mesh.source
    if source not in ("tsdf", "gaussians"):
        raise ConfigError(f"mesh.source={source!r}: expected tsdf (sensor depth) or gaussians (rendered depth)")
    stride = config.mesh.frame_stride
    if source == "gaussians" and mapping is not None and len(mapping.map):
        poses = mapping.rendering_poses(trajectory)[::stride]
        views, camera = gaussian_views(mapping.map.world_gaussians(), mapping.camera, poses), mapping.camera
    else:
        if source == "gaussians":
            logger.warning("mesh.source=gaussians but no Gaussian map was built (mapper.enabled=false?): fusing sensor depth")
        views, camera = sensor_views(sequence, trajectory.world_from_camera, stride), sequence.camera
    write_mesh(path, fuse_tsdf_mesh(views, camera, config.mesh))


def log_final_state(live_view: RerunViewer, sequence: RgbdSequence, tracking: FrontendResult,
                    mapping: MappingStage | None) -> None:
    """After the frontend: corrected keyframes, the sparse map, the Gaussian centres and a render of the last view."""
    last = len(sequence) - 1
    stamp = float(sequence.timestamps_s[last])
    live_view.log_keyframes(last, stamp, tracking.keyframe_trajectory.world_from_camera)
    if len(tracking.map_points_world_m):
        live_view.log_sparse_map(last, stamp, tracking.map_points_world_m, tracking.map_point_colours)
    if mapping is not None and len(mapping.map):
        gaussians = mapping.map.world_gaussians()
        live_view.log_gaussians(last, stamp, gaussians.means_m.detach().cpu().numpy(), gaussians.rgb.detach().cpu().numpy(),
                                gaussians.log_radii_m.detach().exp().cpu().numpy())
        pose = mapping.rendering_poses(tracking.trajectory)[last]
        live_view.log_render(last, stamp, _uint8(mapping.map.render(mapping.camera, pose).rgb.detach().cpu().numpy()))


def write_run_report(output_dir: Path, metrics: dict, sequence: RgbdSequence, errors: TrajectoryErrors | None,
                     mapping: MappingStage | None, trajectory: Trajectory, gaussian_counts: list[tuple[int, int]]) -> None:
    """``output_dir/report/index.html``; adds COLMAP when ``output_dir/colmap/trajectory.txt`` exists."""
    trajectory_errors = {}
    if errors is not None:
        trajectory_errors["tambridge (SE(3))"] = errors
        colmap_path = output_dir / "colmap" / "trajectory.txt"
        if colmap_path.is_file():
            trajectory_errors["COLMAP (Sim(3))"] = evaluate_trajectory(read_tum_trajectory(colmap_path),
                                                                       sequence.ground_truth, align="sim3")
    pairs = []
    if mapping is not None and len(mapping.map):
        poses = mapping.rendering_poses(trajectory)
        for index in np.unique(np.linspace(0, len(sequence) - 1, REPORT_RENDERS).astype(int)):
            rendered = mapping.map.render(mapping.camera, poses[index]).rgb.detach().cpu().numpy()
            pairs.append(RenderPair(f"frame {index}", _uint8(mapping.images(int(index)).rgb.cpu().numpy()), _uint8(rendered)))
    counts = np.array(gaussian_counts).reshape(-1, 2)
    write_report(output_dir / "report", metrics, trajectory_errors, pairs,
                 (counts[:, 0], counts[:, 1]) if len(counts) else None, title=f"tambridge: {metrics['sequence']}")


def _uint8(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) float colours in [0, 1] (clipped) as uint8."""
    return (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
