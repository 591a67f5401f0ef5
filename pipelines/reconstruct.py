"""``tambridge reconstruct``: sequence -> frontend -> (bridge -> mapper) -> exporters -> evaluation.

Every output is written atomically; ``metrics.json`` is written last, so its presence says the run finished.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import logging
import time
from pathlib import Path
from typing import Iterator

import numpy as np
import torch
from tqdm import tqdm

from tambridge.checkpoint import (
    CHECKPOINT_FOLDER,
    CHECKPOINT_NAME,
    Checkpoint,
    KeyframeCheckpoints,
    check_resumable,
    checkpoint_path,
    find_checkpoint,
    remove_checkpoint,
    sequence_fingerprint,
)
from tambridge.config import Config, check_config, config_for_camera, to_dict, to_yaml
from tambridge.device import device_summary, resolve_device
from tambridge.errors import TambridgeError, TrackingFailedError
from tambridge.evaluation.exported import ExportedMap
from tambridge.evaluation.mapping import evaluation_frames, mapping_metrics
from tambridge.evaluation.metrics import DeviceMetrics, RunMetrics, TrajectoryMetrics, WorldMetrics, write_metrics
from tambridge.evaluation.report import REPORT_FILES, write_run_report
from tambridge.evaluation.trajectory import TrajectoryErrors, TrajectoryEvaluationError, evaluate_trajectory
from tambridge.export.config import ExportWorld
from tambridge.export.mesh import run_mesh, write_mesh
from tambridge.export.sparse_map import write_sparse_map
from tambridge.export.splats import save_ply
from tambridge.export.world import WorldFrame, find_world
from tambridge.files import atomic_write_text
from tambridge.frontend.contract import Frontend, FrontendResult
from tambridge.frontend.factory import make_frontend
from tambridge.frontend.smoothing import median_depth_m, smoothed_result
from tambridge.io.prefetch import FramePrefetcher
from tambridge.io.tum import MAX_ASSOCIATION_DIFFERENCE_S, RgbdSequence, find_accelerometer, open_sequence
from tambridge.mapping.stage import MappingStage
from tambridge.run_folder import RunFolder, Start, check_output_folder
from tambridge.runlog import RunLog, peak_memory_mb
from tambridge.stop import RunStopped, StopRequests, signal_name
from tambridge.trajectory import Trajectory, write_tum_trajectory
from tambridge.viewer import RerunViewer, check_viewer_spec, log_final_state

logger = logging.getLogger("tambridge.pipelines.reconstruct")

RUN_FILES = ("config.yaml", "run.log", "trajectory.txt", "keyframes.txt", "sparse_map.npz", "splats.ply", "mesh.ply",
             *(f"report/{name}" for name in REPORT_FILES), CHECKPOINT_FOLDER + "/" + CHECKPOINT_NAME, "metrics.json")
"""Every file a run may write, relative to its output folder (its manifest lists them)."""
SCALE_WARNING_FACTOR = 1.5
"""How far (a factor either way) the Sim(3) fit of a run to its ground truth may scale it before the run warns."""
SCALE_CHECK_MIN_PATH_M = 0.2
"""The ground truth's path length below which a Sim(3) scale says too little to warn of."""
MANY_UNPAIRED_SHARE = 0.05
MANY_UNPAIRED_COUNT = 10
"""The run warns (on the console) rather than only logs it where more than this share of rgb.txt's colour images, and
at least this many, have no depth image: TUM's own recordings leave out a few, mostly before depth starts."""


@dataclasses.dataclass
class ReconstructResult:
    """What a run produced: the per-frame and keyframe trajectories (as trajectory.txt and keyframes.txt hold them, in
    the exported world), the metrics written to metrics.json, the output folder."""

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
    scene_depths_m: list[float] = dataclasses.field(default_factory=list)
    """Each frame's median depth (m, NaN where it has none; :func:`median_depth_m`), in frame order: the depth of
    the scene it sees, for the smoothing."""

    def elapsed_s(self) -> float:
        """Seconds since the run started (a resumed run's include those of the run it continues)."""
        return time.perf_counter() - self.started_s

    def state_dict(self) -> dict:
        return {"elapsed_s": self.elapsed_s(), "keyframes": self.keyframes, "gaussian_counts": list(self.gaussian_counts),
                "frames_without_depth": list(self.frames_without_depth),
                "scene_depths_m": np.array(self.scene_depths_m, np.float64)}

    def load_state_dict(self, state: dict) -> None:
        """Continue the counts of ``state``; the clock goes on from its elapsed seconds."""
        self.started_s -= state["elapsed_s"]
        self.keyframes = state["keyframes"]
        self.gaussian_counts = list(state["gaussian_counts"])
        self.frames_without_depth = list(state["frames_without_depth"])
        self.scene_depths_m = state["scene_depths_m"].tolist()


def reconstruct(
    sequence_dir: Path, output_dir: Path, config: Config, progress: bool = True, viewer: str | None = None,
    start: Start = Start.NEW,
) -> ReconstructResult:
    """Reconstruct a TUM-layout sequence into ``output_dir`` (see docs/design.md for the folder's contents).

    ``viewer``: ``"rerun"`` streams the run to a spawned rerun viewer, ``"rerun:FILE.rrd"`` saves a recording.
    ``start``: what to do with an earlier run in ``output_dir`` (:class:`~tambridge.run_folder.Start`); with
    ``Start.RESUME`` the run continues from ``output_dir/checkpoint/`` and ends as an uninterrupted run would.
    Every input is checked before anything in ``output_dir`` is touched.
    """
    check_config(config)
    if viewer:
        check_viewer_spec(viewer)
    device = resolve_device(config.device)
    output_dir = Path(output_dir)
    checkpoint_file = checkpoint_path(output_dir)
    check_output_folder(output_dir, start, [str(checkpoint_file.relative_to(output_dir))])
    # A run killed before its first checkpoint resumes from the first frame: --resume always ends with every pose.
    checkpoint = find_checkpoint(checkpoint_file) if start is Start.RESUME else None
    read_started = time.perf_counter()
    sequence = open_sequence(
        sequence_dir,
        camera_file=None if config.input.camera_file is None else Path(config.input.camera_file),
        stride=config.input.stride,
        max_frames=config.input.max_frames,
    )
    accelerometer = find_accelerometer(sequence.folder) if config.export.world == ExportWorld.upright else None
    read_seconds = time.perf_counter() - read_started
    # config.yaml records the values the run uses: the ORB settings as adapted to this camera's image size.
    config = config_for_camera(config, sequence.camera)
    fingerprint = sequence_fingerprint(sequence)
    if checkpoint is not None:
        check_resumable(checkpoint_file, checkpoint, to_dict(config), fingerprint)

    with RunFolder(output_dir, start, RUN_FILES), RunLog(output_dir / "run.log", append=checkpoint is not None) as run_log, \
            StopRequests() as stops, saying_the_run_is_unfinished(output_dir, checkpoint_file):
        run_log.add_seconds("read", read_seconds)
        logger.info("reconstructing %s into %s: %d frames, camera %s", sequence.folder, output_dir, len(sequence),
                    sequence.camera)
        if sequence.colour_images_without_depth:
            many = many_without_depth(sequence.colour_images_without_depth, sequence.colour_images_listed)
            logger.log(logging.WARNING if many else logging.INFO,
                       "%d of the %d colour images of rgb.txt have no depth image within %g s: left out%s",
                       sequence.colour_images_without_depth, sequence.colour_images_listed,
                       MAX_ASSOCIATION_DIFFERENCE_S, "; check depth.txt" if many else "")
        atomic_write_text(output_dir / "config.yaml", to_yaml(config))
        frontend = make_frontend(config.frontend, sequence.camera)
        mapping = MappingStage(sequence, config.mapper, config.bridge, run_log, device, config.seed,
                               config.frontend.orb.rolling_shutter_s) if config.mapper.enabled else None
        logger.info("Gaussian map, bridge and rendering evaluation on %s", device if mapping is not None else "(mapper off)")
        # The run's clock started with the reading of the sequence, as end to end always has.
        counters = RunCounters(started_s=read_started)
        if start is Start.RESUME and checkpoint is None:
            logger.warning("%s: no checkpoint (the run here stopped before its first one, or there is none): "
                           "starting from the first frame", checkpoint_file)
        start_frame = 0 if checkpoint is None else restore_run(checkpoint, frontend, mapping, run_log, counters)
        checkpoints = None
        if config.checkpoint.every_keyframes:
            snapshot = functools.partial(run_checkpoint, config=config, fingerprint=fingerprint, frontend=frontend,
                                         mapping=mapping, run_log=run_log, counters=counters)
            checkpoints = KeyframeCheckpoints(checkpoint_file, config.checkpoint.every_keyframes, snapshot,
                                              counters.keyframes, config.checkpoint.min_interval_s,
                                              config.checkpoint.max_time_share, config.checkpoint.max_interval_s)
        with contextlib.ExitStack() as viewing:
            live_view = RerunViewer(viewer, sequence.camera) if viewer else None
            if live_view is not None:
                viewing.callback(live_view.close)

            tracking = track_frames(sequence, frontend, mapping, counters, run_log, start_frame=start_frame,
                                    prefetch=config.frontend.prefetch, progress=progress, checkpoints=checkpoints,
                                    live_view=live_view, stops=stops)
            check_tracked(sequence, tracking)
            # The peak of the online part (tracking and mapping every frame); exports and evaluation come after it.
            peak_memory_tracking_mb = peak_memory_mb()
            tracking = smoothed_result(tracking, config.frontend.smoothing, np.array(counters.scene_depths_m))
            gaussians = mesh = None
            if mapping is not None:
                # The frames the evaluation scores as novel views stay out of the map.
                mapping.finish(tracking.keyframe_poses, tracking,
                               held_out=evaluation_frames(len(sequence), config.evaluation.novel_view_every, set()))
                gaussians = mapping.map.world_gaussians()
            if config.mesh.enabled:
                with run_log.stage("mesh"):
                    mesh = run_mesh(sequence, tracking.trajectory, config.mesh, mapping)
            with run_log.stage("export"):
                world = find_world(config.export.world, tracking.trajectory, accelerometer,
                                   surface_points(mesh, gaussians, tracking), config.seed)
                write_exports(output_dir, world, tracking, gaussians, mesh)
            if live_view is not None:
                with run_log.stage("viewer"):
                    log_final_state(live_view, sequence, tracking, mapping)
        # Scored and shown as a viewer reads them: the files just written, loaded once.
        exported = None if mapping is None else ExportedMap.from_run(output_dir, config.mapper, device)
        metrics, errors = evaluate_run(sequence, config, tracking, mapping, exported, device, run_log, counters,
                                       peak_memory_tracking_mb)
        metrics.world = WorldMetrics(**world.summary())
        metrics.sequence_fingerprint = fingerprint
        write_run_report(output_dir, metrics, sequence, errors, mapping, exported, tracking.trajectory,
                         counters.gaussian_counts)
        write_metrics(output_dir / "metrics.json", metrics)
        # The run is whole: nothing is left to resume.
        remove_checkpoint(output_dir)
        logger.info("finished in %.1f s", metrics.seconds_total)
        return ReconstructResult(world.trajectory(tracking.trajectory), world.trajectory(tracking.keyframe_trajectory),
                                 metrics, output_dir)


def many_without_depth(without_depth: int, listed: int) -> bool:
    """Whether ``without_depth`` of ``listed`` colour images without a depth image say that depth.txt lacks frames
    (:data:`MANY_UNPAIRED_SHARE`, :data:`MANY_UNPAIRED_COUNT`)."""
    return without_depth > MANY_UNPAIRED_SHARE * listed and without_depth >= MANY_UNPAIRED_COUNT


@contextlib.contextmanager
def saying_the_run_is_unfinished(output_dir: Path, checkpoint_file: Path) -> Iterator[None]:
    """Re-raise an input error met mid-run (a frame that cannot be decoded; no frame tracked), of the same class,
    saying what ``output_dir`` now holds and how to go on; likewise a stop by a signal that came outside the tracking
    loop (the map's last rounds, the mesh, the evaluation: :class:`RunStopped` ``at_once``), where the loop's own
    stops say so themselves."""
    try:
        yield
    except RunStopped as stop:
        if not stop.at_once:
            raise
        if not checkpoint_file.is_file():
            raise RunStopped(stop.signum, f"{stop}; {output_dir} holds the unfinished run, with no checkpoint: run again "
                                          "to start over") from None
        # run.log says which frame the latest checkpoint is at; reading the checkpoint here could take seconds.
        raise RunStopped(stop.signum, f"{stop}; {output_dir} keeps its latest checkpoint: the same command with --resume "
                                      "continues there") from None
    except TambridgeError as error:
        go_on = "the same command replaces it once that is fixed"
        if checkpoint_file.is_file():
            go_on = ("--overwrite starts it again once that is fixed (--resume continues it only where the sequence "
                     "and settings are unchanged)")
        raise type(error)(f"{error} ({output_dir} holds the unfinished run: {go_on})") from error


def surface_points(mesh, gaussians, tracking: FrontendResult) -> np.ndarray:
    """Points (P, 3) on the scene's surfaces (first-camera world) for the plane search of the upright world: the
    mesh's vertices (even over surfaces) where there is a mesh, else the Gaussians' means, else the frontend's map
    points (none for Open3D)."""
    if mesh is not None and len(mesh.vertices):
        return np.asarray(mesh.vertices, np.float64)
    if gaussians is not None and len(gaussians):
        return gaussians.means_m.detach().cpu().numpy().astype(np.float64)
    return np.asarray(tracking.map_points_world_m, np.float64).reshape(-1, 3)


def write_exports(output_dir: Path, world: WorldFrame, tracking: FrontendResult, gaussians, mesh) -> None:
    """Write trajectory.txt, keyframes.txt, sparse_map.npz, splats.ply and mesh.ply (the last two where given) in
    ``world``: every pose and point goes through it here, once."""
    write_tum_trajectory(output_dir / "trajectory.txt", world.trajectory(tracking.trajectory))
    write_tum_trajectory(output_dir / "keyframes.txt", world.trajectory(tracking.keyframe_trajectory))
    write_sparse_map(output_dir / "sparse_map.npz", world.frontend_result(tracking))
    if gaussians is not None:
        save_ply(output_dir / "splats.ply", world.gaussians(gaussians))
    if mesh is not None:
        write_mesh(output_dir / "mesh.ply", world.mesh(mesh))


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
    stops: StopRequests | None = None,
) -> FrontendResult:
    """Track every frame from ``start_frame`` on, in order, mapping each keyframe (bridge, then mapper) as it comes;
    returns the frontend's final result (after loop closure and global BA). With ``checkpoints`` and ``mapping``, the
    state after the last frame is checkpointed too, before the frontend's finish, where this call tracked a frame
    after the first (without the Gaussian map what follows takes seconds, and none is written).

    After each frame ``counters`` count it, the mapping stage may ask the frontend for a keyframe where its map lacks
    coverage, ``live_view`` shows it and ``checkpoints`` are told of it (once it is mapped).
    ``prefetch``: the next frames (:data:`~tambridge.io.prefetch.FRAMES_AHEAD`) are read in one worker thread and their
    ``frontend.extract`` (where the frontend has one) made in another while frame i is tracked
    (:class:`FramePrefetcher`), with the results of reading and tracking one frame after the other. Stage
    "frame_reading" is the time spent waiting for the next frame (reading it, or with ``prefetch`` what its reading and
    extraction did not hide behind tracking); "tracking" is the rest of the frontend's time; mapping a keyframe is not
    tracking.
    """
    with FramePrefetcher(sequence, start_frame, frontend.extract if prefetch else None, read_ahead=prefetch) as prefetcher, \
            stops.deferred() if stops is not None else contextlib.nullcontext():
        frames = iter(prefetcher)
        tracked_after_first = False
        for index in tqdm(range(start_frame, len(sequence)), total=len(sequence), initial=start_frame,
                          desc="tracking", unit="frame", disable=not progress):
            with run_log.stage("frame_reading"):
                frame, features = next(frames)
            with run_log.stage("tracking"):
                result = frontend.track(frame, features)
            tracked_after_first |= result.tracked and index > 0
            if mapping is not None:
                mapping.on_tracked(result, frame, prefetcher.sharpness.pop(frame.index, None))
            if mapping is not None and result.keyframe is not None:
                mapping.on_keyframe(result.keyframe, frame, frontend.keyframe_poses())
            counters.keyframes += result.is_keyframe
            counters.scene_depths_m.append(median_depth_m(frame.depth_m))
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
            if checkpoints is not None:
                with run_log.stage("checkpoint"):
                    checkpoints.after_frame(index + 1, result.is_keyframe)
            if stops is not None and stops.requested is not None:
                stop_after_frame(stops.requested, index + 1, len(sequence), checkpoints, run_log)
        if checkpoints is not None and tracked_after_first and mapping is not None:
            # What follows (global BA, the map's last rounds, mesh, evaluation) can take as long again: a stop there
            # resumes from here rather than from the last keyframe's checkpoint. Without the Gaussian map what follows
            # takes seconds, and writing the checkpoint would cost every run a part of that. (Where no frame
            # tracked, the run fails next: nothing is worth resuming.)
            with run_log.stage("checkpoint"):
                checkpoints.write_unless_written(len(sequence))
        if stops is not None and stops.requested is not None:
            # A signal while that checkpoint was written.
            stop_after_frame(stops.requested, len(sequence), len(sequence), checkpoints, run_log)
    with run_log.stage("tracking"):
        return frontend.finish()


def check_tracked(sequence: RgbdSequence, tracking: FrontendResult) -> None:
    """Refuse to write a trajectory in which no frame after the first was tracked (it would be the first pose
    repeated, or a constant-velocity guess): a :class:`TrackingFailedError` before any result is written."""
    if len(sequence) > 1 and not np.asarray(tracking.tracked)[1:].any():
        raise TrackingFailedError(
            f"{sequence.folder}: none of the {len(sequence) - 1} frames after the first could be tracked (run.log says "
            "why for each); check that the images have texture and depth and that the camera file fits them")


def stop_after_frame(signum: int, next_frame: int, frame_count: int, checkpoints: KeyframeCheckpoints | None,
                     run_log: RunLog) -> None:
    """Honour a stop signal between frames: write a checkpoint at ``next_frame`` (with checkpoints on) and raise
    :class:`RunStopped` saying where the run stopped and how to go on."""
    where = f"stopped by {signal_name(signum)} after frame {next_frame} of {frame_count}"
    if checkpoints is None:
        raise RunStopped(signum, f"{where}; no checkpoint (checkpoint.every_keyframes=0): run again to start over",
                         at_once=False)
    with run_log.stage("checkpoint"):
        checkpoints.write_unless_written(next_frame)
    raise RunStopped(signum, f"{where}; checkpoint written: the same command with --resume continues there",
                     at_once=False)


def run_checkpoint(next_frame: int, *, config: Config, fingerprint: dict, frontend: Frontend,
                   mapping: MappingStage | None, run_log: RunLog, counters: RunCounters) -> Checkpoint:
    """The checkpoint of a run that has tracked and mapped frames ``[0, next_frame)`` of the sequence of
    ``fingerprint``."""
    run = {"stage_seconds": dict(run_log.stage_seconds), "warnings": run_log.warnings, **counters.state_dict()}
    return Checkpoint(next_frame, to_dict(config), fingerprint, frontend.state_dict(),
                      None if mapping is None else mapping.state_dict(), run)


def restore_run(checkpoint: Checkpoint, frontend: Frontend, mapping: MappingStage | None, run_log: RunLog,
                counters: RunCounters) -> int:
    """Load ``checkpoint`` (checked by :func:`check_resumable`) into the fresh frontend, mapping stage, ``run_log``
    and ``counters``; returns the next frame to track."""
    frontend.load_state_dict(checkpoint.frontend)
    if mapping is not None:
        mapping.load_state_dict(checkpoint.mapping)
    run = checkpoint.run
    for stage, seconds in run["stage_seconds"].items():
        run_log.add_seconds(stage, seconds)
    run_log.warnings += run["warnings"]
    counters.load_state_dict(run)
    logger.info("resuming at frame %d of %d (%d keyframes)", checkpoint.next_frame, checkpoint.sequence["frames"],
                counters.keyframes)
    return checkpoint.next_frame


def evaluate_run(sequence: RgbdSequence, config: Config, tracking: FrontendResult, mapping: MappingStage | None,
                 exported: ExportedMap | None, device: torch.device, run_log: RunLog, counters: RunCounters,
                 peak_memory_tracking_mb: float) -> tuple[RunMetrics, TrajectoryErrors | None]:
    """The run's metrics, and its trajectory's errors against the ground truth (None without one).

    The map is scored as the run holds it and as ``exported`` (splats.ply and trajectory.txt read back; None
    exactly when ``mapping`` is).
    The run's clock stops here: the map's rendering evaluation and the trajectory's are not part of it.
    """
    # End to end = what a user waits for to get trajectory and map.
    seconds_total = counters.elapsed_s()
    fps_per_stage = {name: len(sequence) / max(seconds, 1e-9) for name, seconds in run_log.stage_seconds.items()}
    map_metrics = None
    if mapping is not None:
        map_metrics = mapping_metrics(mapping, tracking, sequence, config.evaluation, run_log, exported)
    metrics = RunMetrics(
        sequence=str(Path(sequence.folder).resolve()),
        frames=len(sequence),
        keyframes=len(tracking.keyframe_trajectory),
        frontend=config.frontend.kind,
        frames_lost=tracking.frames_lost,
        frames_relocalised=tracking.frames_relocalised,
        frames_tracked_by_depth=tracking.frames_tracked_by_depth,
        frames_without_depth=len(counters.frames_without_depth),
        colour_images_without_depth=sequence.colour_images_without_depth,
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
        trajectory_unavailable=None,
        map=map_metrics,
        # The frontend, the mesh and the exporters run on the CPU: the device is the mapping stage's.
        device=DeviceMetrics(**device_summary(device)) if mapping is not None else DeviceMetrics(device="cpu"),
    )
    if sequence.ground_truth is None:
        metrics.trajectory_unavailable = "the sequence has no groundtruth.txt"
        return metrics, None
    try:
        errors = evaluate_trajectory(tracking.trajectory, sequence.ground_truth, align="se3")
    except TrajectoryEvaluationError as error:
        # The run's other outputs are whole: say why there is no ATE rather than lose them.
        metrics.trajectory_unavailable = str(error)
        logger.warning("no ATE: %s", error)
        return metrics, None
    metrics.trajectory = TrajectoryMetrics(**errors.summary())
    logger.info("ATE RMSE %.2f cm over %d poses (SE(3)-aligned)", errors.ate_rmse_m * 100, errors.pose_count)
    warn_of_a_scale_off(tracking.trajectory, sequence)
    return metrics, errors


def warn_of_a_scale_off(trajectory: Trajectory, sequence: RgbdSequence) -> None:
    """Warn where the Sim(3) fit to the ground truth sizes the trajectory :data:`SCALE_WARNING_FACTOR` times or more
    off, over a path of :data:`SCALE_CHECK_MIN_PATH_M` or more: the depth scale's plausibility check (median depth in
    0.1-10 m) passes a ``depth_scale`` 5 times too large, which shrinks the whole reconstruction."""
    fit = evaluate_trajectory(trajectory, sequence.ground_truth, align="sim3")
    path_m = float(np.linalg.norm(np.diff(fit.ref.world_from_camera[:, :3, 3], axis=0), axis=1).sum())
    if path_m >= SCALE_CHECK_MIN_PATH_M and np.isfinite(fit.scale) and fit.scale > 0 \
            and abs(np.log(fit.scale)) >= np.log(SCALE_WARNING_FACTOR):
        logger.warning("the trajectory is %.3g times the size of groundtruth.txt's (Sim(3) fit over %.2f m of path): a "
                       "depth_scale off by that factor? depth_scale %g would fit (camera.yaml, --camera)", 1.0 / fit.scale,
                       path_m, sequence.sensor.depth_scale / fit.scale)
