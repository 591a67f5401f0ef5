"""``tambridge reconstruct``: sequence -> frontend -> (bridge -> mapper) -> exporters -> evaluation.

Every output is written atomically; ``metrics.json`` is written last, so its presence says the run finished.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from tambridge.checkpoint import (
    Checkpoint,
    KeyframeCheckpoints,
    check_resumable,
    checkpoint_path,
    load_checkpoint,
    sequence_fingerprint,
)
from tambridge.config import Config, check_config, config_for_camera, to_dict, to_yaml
from tambridge.device import device_summary, resolve_device
from tambridge.evaluation.mapping import mapping_metrics
from tambridge.evaluation.metrics import DeviceMetrics, RunMetrics, TrajectoryMetrics, write_metrics
from tambridge.evaluation.report import RenderPair, write_report
from tambridge.evaluation.trajectory import TrajectoryErrors, evaluate_trajectory
from tambridge.export.config import MeshSource
from tambridge.export.mesh import fuse_tsdf_mesh, gaussian_views, sensor_views, write_mesh
from tambridge.export.sparse_map import write_sparse_map
from tambridge.export.splats import save_ply
from tambridge.files import atomic_write_text
from tambridge.frontend.contract import Frontend, FrontendResult
from tambridge.frontend.factory import make_frontend
from tambridge.io.prefetch import FramePrefetcher
from tambridge.io.tum import RgbdSequence, open_sequence
from tambridge.mapping.stage import MappingStage
from tambridge.runlog import RunLog, peak_memory_mb
from tambridge.trajectory import Trajectory, read_tum_trajectory, write_tum_trajectory
from tambridge.viewer import RerunViewer

logger = logging.getLogger("tambridge.pipelines.reconstruct")

RESULTS = ("metrics.json", "trajectory.txt", "keyframes.txt", "sparse_map.npz", "splats.ply", "mesh.ply", "report/index.html")
"""What a run writes beside config.yaml and run.log, relative to its output folder."""


@dataclasses.dataclass
class ReconstructResult:
    """What a run produced: the per-frame trajectory, the metrics written to metrics.json, the output folder."""

    trajectory: Trajectory
    keyframes: Trajectory
    metrics: RunMetrics
    output_dir: Path


@dataclasses.dataclass
class RunCounters:
    """What a run counts itself, beside its stages' state; a checkpoint keeps it (:meth:`state_dict`)."""

    started_s: float = dataclasses.field(default_factory=time.perf_counter)
    """``time.perf_counter()`` when the run started; a resumed run's lies back by the seconds the killed run took."""
    keyframes: int = 0
    gaussian_counts: list[tuple[int, int]] = dataclasses.field(default_factory=list)
    """(frame index, Gaussians in the map after that frame), with the mapper on."""
    frames_without_depth: list[int] = dataclasses.field(default_factory=list)

    def elapsed_s(self) -> float:
        """Seconds since the run started (a resumed run's include those of the run it continues)."""
        return time.perf_counter() - self.started_s

    def state_dict(self) -> dict:
        return {"elapsed_s": self.elapsed_s(), "keyframes": self.keyframes, "gaussian_counts": list(self.gaussian_counts),
                "frames_without_depth": list(self.frames_without_depth)}

    def load_state_dict(self, state: dict) -> None:
        """Continue the counts of ``state``; the clock goes on from its elapsed seconds."""
        self.started_s -= state["elapsed_s"]
        self.keyframes = state["keyframes"]
        self.gaussian_counts = list(state["gaussian_counts"])
        self.frames_without_depth = list(state["frames_without_depth"])


def reconstruct(
    sequence_dir: Path, output_dir: Path, config: Config, progress: bool = True, viewer: str | None = None,
    resume: bool = False,
) -> ReconstructResult:
    """Reconstruct a TUM-layout sequence into ``output_dir`` (see DESIGN.md for the folder's contents).

    ``viewer``: ``"rerun"`` streams the run to a spawned rerun viewer, ``"rerun:FILE.rrd"`` saves a recording.
    ``resume``: continue from ``output_dir/checkpoint/`` (written every ``checkpoint.every_keyframes`` keyframes by
    a run with the same config and sequence); the result is that of an uninterrupted run.
    """
    # Before anything is read or removed: a bad value, or a GPU the run cannot have, stops it here.
    check_config(config)
    device = resolve_device(config.device)
    output_dir = Path(output_dir)
    checkpoint_file = checkpoint_path(output_dir)
    # Before anything is removed: --resume on a finished run (no checkpoint) must not cost its results.
    checkpoint = load_checkpoint(checkpoint_file) if resume else None
    remove_results(output_dir, checkpoint_file if not resume else None)
    run_log = RunLog(output_dir / "run.log", append=resume)
    counters = RunCounters()
    live_view = None
    try:
        logger.info("reconstructing %s into %s", sequence_dir, output_dir)
        with run_log.stage("read"):
            sequence = open_sequence(
                sequence_dir,
                camera_file=None if config.input.camera_file is None else Path(config.input.camera_file),
                stride=config.input.stride,
                max_frames=config.input.max_frames,
            )
        logger.info("%d frames, camera %s", len(sequence), sequence.camera)
        # config.yaml records the values the run uses: the ORB settings as adapted to this camera's image size.
        config = config_for_camera(config, sequence.camera.width, sequence.camera.height)
        atomic_write_text(output_dir / "config.yaml", to_yaml(config))
        frontend = make_frontend(config.frontend, sequence.camera)
        mapping = MappingStage(sequence, config, run_log, device) if config.mapper.enabled else None
        logger.info("Gaussian map, bridge and rendering evaluation on %s", device if mapping is not None else "(mapper off)")
        live_view = RerunViewer(viewer, sequence.camera) if viewer else None
        fingerprint = sequence_fingerprint(sequence.folder, sequence.timestamps_s, sequence.sensor)
        start_frame = 0
        if checkpoint is not None:
            start_frame = restore_run(checkpoint_file, checkpoint, config, fingerprint, frontend, mapping, run_log, counters)
        checkpoints = None
        if config.checkpoint.every_keyframes:
            snapshot = functools.partial(run_checkpoint, config=config, fingerprint=fingerprint, frontend=frontend,
                                         mapping=mapping, run_log=run_log, counters=counters)
            checkpoints = KeyframeCheckpoints(checkpoint_file, config.checkpoint.every_keyframes, snapshot, counters.keyframes)

        tracking = track_frames(sequence, frontend, mapping, counters, run_log, start_frame=start_frame,
                                prefetch=config.frontend.prefetch, progress=progress, checkpoints=checkpoints,
                                live_view=live_view)
        # The peak of the online part (tracking and mapping every frame); exports and evaluation come after it.
        peak_memory_tracking_mb = peak_memory_mb()
        write_tum_trajectory(output_dir / "trajectory.txt", tracking.trajectory)
        write_tum_trajectory(output_dir / "keyframes.txt", tracking.keyframe_trajectory)
        write_sparse_map(output_dir / "sparse_map.npz", tracking, sequence.folder)
        if mapping is not None:
            mapping.finish(tracking.keyframe_poses)
            with run_log.stage("export"):
                save_ply(output_dir / "splats.ply", mapping.map.world_gaussians())
        if config.mesh.enabled:
            with run_log.stage("mesh"):
                write_run_mesh(output_dir / "mesh.ply", sequence, tracking.trajectory, config, mapping)
        if live_view is not None:
            with run_log.stage("viewer"):
                log_final_state(live_view, sequence, tracking, mapping)
        metrics, errors = evaluate_run(sequence_dir, sequence, config, tracking, mapping, device, run_log, counters,
                                       peak_memory_tracking_mb)
        write_run_report(output_dir, metrics, sequence, errors, mapping, tracking.trajectory, counters.gaussian_counts)
        write_metrics(output_dir / "metrics.json", metrics)
        # The run is whole: nothing is left to resume.
        checkpoint_file.unlink(missing_ok=True)
        logger.info("finished in %.1f s", metrics.seconds_total)
        return ReconstructResult(tracking.trajectory, tracking.keyframe_trajectory, metrics, output_dir)
    except BaseException as error:
        run_log.record_stop(error)
        raise
    finally:
        if live_view is not None:
            live_view.close()
        run_log.close()


def remove_results(output_dir: Path, checkpoint_file: Path | None) -> None:
    """Make ``output_dir`` and remove an earlier run's :data:`RESULTS` from it (and ``checkpoint_file`` unless None):
    a re-run into the same folder must not leave them looking like this run's."""
    output_dir.mkdir(parents=True, exist_ok=True)
    for stale in [output_dir / name for name in RESULTS] + ([checkpoint_file] if checkpoint_file is not None else []):
        stale.unlink(missing_ok=True)


def track_frames(
    sequence: RgbdSequence,
    frontend: Frontend,
    mapping: MappingStage | None,
    counters: RunCounters,
    run_log: RunLog,
    start_frame: int = 0,
    prefetch: bool = True,
    progress: bool = False,
    checkpoints: KeyframeCheckpoints | None = None,
    live_view: RerunViewer | None = None,
) -> FrontendResult:
    """Track every frame from ``start_frame`` on, in order, mapping each keyframe (bridge, then mapper) as it comes;
    returns the frontend's final result (after loop closure and global BA).

    After each frame ``counters`` count it, the mapping stage may ask the frontend for a keyframe where its map lacks
    coverage, ``live_view`` shows it and ``checkpoints`` are told of a keyframe (once it is mapped).
    ``prefetch``: frame i+2 is read in one worker thread and frame i+1's ``frontend.extract`` (where the frontend has
    one) made in another while frame i is tracked (:class:`FramePrefetcher`), with the results of reading and
    tracking one frame after the other. Stage "frame_reading" is the time spent waiting for the next frame (reading
    it, or with ``prefetch`` what its reading and extraction did not hide behind tracking); "tracking" is the rest of
    the frontend's time; mapping a keyframe is not tracking.
    """
    with FramePrefetcher(sequence, start_frame, frontend.extract if prefetch else None, read_ahead=prefetch) as prefetcher:
        frames = iter(prefetcher)
        for index in tqdm(range(start_frame, len(sequence)), total=len(sequence), initial=start_frame,
                          desc="tracking", unit="frame", disable=not progress):
            with run_log.stage("frame_reading"):
                frame, features = next(frames)
            with run_log.stage("tracking"):
                result = frontend.track(frame, features)
            if mapping is not None and result.keyframe is not None:
                mapping.on_keyframe(result.keyframe, frame, frontend.keyframe_poses())
            counters.keyframes += result.is_keyframe
            if not (frame.depth_m > 0).any():
                # A frame without depth still tracks from colour (PnP on the map) but adds nothing to either map.
                counters.frames_without_depth.append(frame.index)
                logger.warning("frame %d (t=%.6f): no valid depth in %s; %s", frame.index, frame.timestamp_s,
                               sequence.depth_paths[frame.index].name,
                               "tracked from colour" if result.tracked else "not tracked")
            if mapping is not None:
                counters.gaussian_counts.append((frame.index, len(mapping.map)))
                if mapping.needs_view(result, frame):
                    frontend.request_keyframe()
            if live_view is not None:
                with run_log.stage("viewer"):
                    live_view.log_frame(frame.index, frame.timestamp_s, result.world_from_camera, frame.rgb,
                                        frame.depth_m, result.is_keyframe)
            if checkpoints is not None and result.is_keyframe:
                with run_log.stage("checkpoint"):
                    checkpoints.after_keyframe(index + 1)
    with run_log.stage("tracking"):
        return frontend.finish()


def run_checkpoint(next_frame: int, *, config: Config, fingerprint: dict, frontend: Frontend,
                   mapping: MappingStage | None, run_log: RunLog, counters: RunCounters) -> Checkpoint:
    """The checkpoint of a run that has tracked and mapped frames ``[0, next_frame)`` of the sequence of
    ``fingerprint``."""
    run = {"stage_seconds": dict(run_log.stage_seconds), "warnings": run_log.warnings, **counters.state_dict()}
    return Checkpoint(next_frame, to_dict(config), fingerprint, frontend.state_dict(),
                      None if mapping is None else mapping.state_dict(), run)


def restore_run(checkpoint_file: Path, checkpoint: Checkpoint, config: Config, fingerprint: dict, frontend: Frontend,
                mapping: MappingStage | None, run_log: RunLog, counters: RunCounters) -> int:
    """Check that ``checkpoint`` (read from ``checkpoint_file``) is of this config and sequence, then load it into the
    fresh frontend, mapping stage, ``run_log`` and ``counters``; returns the next frame to track."""
    check_resumable(checkpoint_file, checkpoint, to_dict(config), fingerprint)
    frontend.load_state_dict(checkpoint.frontend)
    if mapping is not None:
        mapping.load_state_dict(checkpoint.mapping)
    run = checkpoint.run
    for stage, seconds in run["stage_seconds"].items():
        run_log.stage_seconds[stage] = run_log.stage_seconds.get(stage, 0.0) + seconds
    run_log.warnings += run["warnings"]
    counters.load_state_dict(run)
    logger.info("resuming from %s at frame %d of %d (%d keyframes)", checkpoint_file, checkpoint.next_frame,
                fingerprint["frames"], counters.keyframes)
    return checkpoint.next_frame


def evaluate_run(sequence_dir: Path, sequence: RgbdSequence, config: Config, tracking: FrontendResult,
                 mapping: MappingStage | None, device: torch.device, run_log: RunLog, counters: RunCounters,
                 peak_memory_tracking_mb: float) -> tuple[RunMetrics, TrajectoryErrors | None]:
    """The run's metrics, and its trajectory's errors against the ground truth (None without one).

    The run's clock stops here: the map's rendering evaluation and the trajectory's are not part of it.
    """
    # End to end = what a user waits for to get trajectory and map.
    seconds_total = counters.elapsed_s()
    fps_per_stage = {name: len(sequence) / max(seconds, 1e-9) for name, seconds in run_log.stage_seconds.items()}
    map_metrics = None if mapping is None else mapping_metrics(mapping, tracking, sequence, config, run_log)
    metrics = RunMetrics(
        sequence=str(sequence_dir),
        frames=len(sequence),
        keyframes=len(tracking.keyframe_trajectory),
        frontend=config.frontend.kind,
        frames_lost=tracking.frames_lost,
        frames_relocalised=tracking.frames_relocalised,
        frames_without_depth=len(counters.frames_without_depth),
        loops_closed=tracking.loops_closed,
        keyframes_culled=tracking.keyframes_culled,
        frontend_seconds_per_stage=tracking.timings_s,
        seconds_total=seconds_total,
        fps_end_to_end=len(sequence) / seconds_total,
        seconds_per_stage=dict(run_log.stage_seconds),
        fps_per_stage=fps_per_stage,
        peak_memory_mb=peak_memory_mb(),
        peak_memory_mb_tracking=peak_memory_tracking_mb,
        warnings=run_log.warnings,
        trajectory=None,
        map=map_metrics,
        # The frontend, the mesh and the exporters run on the CPU: the device is the mapping stage's.
        device=DeviceMetrics(**device_summary(device)) if mapping is not None else DeviceMetrics(device="cpu"),
    )
    errors = None
    if sequence.ground_truth is not None:
        errors = evaluate_trajectory(tracking.trajectory, sequence.ground_truth, align="se3")
        metrics.trajectory = TrajectoryMetrics(**errors.summary())
        logger.info("ATE RMSE %.2f cm over %d poses (SE(3)-aligned)", errors.ate_rmse_m * 100, errors.pose_count)
    return metrics, errors


REPORT_RENDERS = 4
"""Frames rendered from the map for the report's grid (at the mapping resolution: cheap)."""


def write_run_mesh(path: Path, sequence: RgbdSequence, trajectory: Trajectory, config: Config,
                   mapping: MappingStage | None) -> None:
    """TSDF mesh of every ``mesh.frame_stride``-th frame at its final pose; ``mesh.source=rendered`` fuses the
    map's rendered depth (at the mapping resolution, from the rendering poses) instead of the sensor's."""
    source = config.mesh.source
    stride = config.mesh.frame_stride
    if source == MeshSource.rendered and mapping is not None and len(mapping.map):
        poses = mapping.rendering_poses(trajectory)[::stride]
        views, camera = gaussian_views(mapping.map.world_gaussians(), mapping.camera, poses), mapping.camera
    else:
        if source == MeshSource.rendered:
            logger.warning("mesh.source=rendered but no Gaussian map was built (mapper.enabled=false?): fusing sensor depth")
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


def write_run_report(output_dir: Path, metrics: RunMetrics, sequence: RgbdSequence, errors: TrajectoryErrors | None,
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
                 (counts[:, 0], counts[:, 1]) if len(counts) else None, title=f"tambridge: {metrics.sequence}")


def _uint8(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) float colours in [0, 1] (clipped) as uint8."""
    return (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
