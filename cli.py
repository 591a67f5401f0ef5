"""``tambridge``: the command line, a thin click layer over pipelines/ and the library."""

from __future__ import annotations

import errno
import json
import logging
import os
import signal
import sys
import tempfile
from pathlib import Path

import click

from tambridge.errors import INPUT_ERROR_STATUS, TambridgeError
from tambridge.export.config import MeshSource
from tambridge.settings import Device
from tambridge.stop import RunStopped, signal_name


def _fail(error: Exception | str, status: int | None = None) -> None:
    """``error`` as one line on stderr, then exit with ``status``: by default the error's own (a run stopped by a
    signal exits as the shell reports one, 143 for SIGTERM, 130 for SIGINT), else that of bad input."""
    click.echo(f"error: {error}", err=True)
    sys.exit(status if status is not None else getattr(error, "exit_status", INPUT_ERROR_STATUS))


_STOPPED_BY_CTRL_C = RunStopped(signal.SIGINT, f"stopped by {signal_name(signal.SIGINT)}")
"""What a Ctrl-C outside a run's own handlers reports (one line, status 130)."""


class _Group(click.Group):
    """Turns tambridge's input errors, click's errors in a command's arguments, the system's refusals to read or
    write a file (permissions, a full disk) and a Ctrl-C while a command runs into one line on stderr, never a
    traceback."""

    def make_context(self, info_name, args, parent=None, **extra):
        try:
            return super().make_context(info_name, args, parent, **extra)
        except KeyboardInterrupt:
            # Ctrl-C while click parses the arguments, before invoke: click itself would print "Aborted!", exit 1.
            _fail(_STOPPED_BY_CTRL_C)

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except TambridgeError as error:
            _fail(error)
        except click.UsageError as error:
            command_path = (error.ctx or ctx).command_path
            _fail(TambridgeError(f"{' '.join(error.format_message().split())} (see {command_path} --help)"))
        except KeyboardInterrupt:
            # Ctrl-C where no run's own handlers are installed (tambridge.stop), e.g. while a command loads its
            # libraries: reported as a run stopped by SIGINT is.
            _fail(_STOPPED_BY_CTRL_C)
        except BrokenPipeError:
            # The reader of the output went away (`tambridge config | head`): nothing to report to it.
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            sys.exit(1)
        except OSError as error:
            fix = OS_ERROR_FIXES.get(error.errno, "check the path")
            # A path the user gave that cannot be used is bad input; a full disk or a failing file system is not,
            # and another attempt (tambridge batch retries) may succeed.
            _fail(f"{error.filename or 'a file'}: {error.strerror or error}; {fix}",
                  SYSTEM_ERROR_STATUS if error.errno in SYSTEM_ERRNOS else INPUT_ERROR_STATUS)
        except (ImportError, RuntimeError) as error:
            # A library that a Ctrl-C interrupted while it loaded may wrap the KeyboardInterrupt in its own error
            # (pycolmap: "Cannot import the C++ backend"): still a Ctrl-C, not a broken install.
            if not _caused_by_ctrl_c(error):
                raise
            _fail(_STOPPED_BY_CTRL_C)


def _caused_by_ctrl_c(error: BaseException) -> bool:
    """Whether a KeyboardInterrupt lies in ``error``'s chain of causes and contexts."""
    seen = set()
    while error is not None and id(error) not in seen:
        if isinstance(error, KeyboardInterrupt):
            return True
        seen.add(id(error))
        error = error.__cause__ or error.__context__
    return False


OS_ERROR_FIXES = {
    errno.ENOSPC: "free some space or write the outputs elsewhere (-o)",
    errno.EDQUOT: "free some of your quota or write the outputs elsewhere (-o)",
    errno.EACCES: "give a path you may read or write, or change its permissions",
    errno.EPERM: "give a path you may read or write, or change its permissions",
    errno.EROFS: "write the outputs to a writable file system (-o)",
    errno.ENAMETOOLONG: "give a shorter path",
    errno.ENOTDIR: "part of the path is a file, not a folder; give another path",
    errno.EISDIR: "is a folder; give a file",
}
"""What a user can do about the system's refusals the CLI reports (by errno); others say to check the path."""

SYSTEM_ERRNOS = frozenset((errno.ENOSPC, errno.EDQUOT, errno.EIO, errno.ESTALE, errno.ENOMEM, errno.ETIMEDOUT,
                           errno.EAGAIN))
"""Refusals that say nothing wrong of the input: the command exits with :data:`SYSTEM_ERROR_STATUS`."""
SYSTEM_ERROR_STATUS = 1


def _output_folder(ctx, param, value):
    """-o as a Path; an empty value (an unset shell variable) would mean the current folder: refused."""
    if value is not None and not str(value).strip():
        raise click.BadParameter("is empty (an unset shell variable?); give the output folder", param=param)
    return None if value is None else Path(value)


@click.group(cls=_Group)
@click.version_option(package_name="tambridge")
def main() -> None:
    """RGB-D SLAM and 3D Gaussian Splatting reconstruction that runs on a CPU."""
    # Only warnings reach the terminal; run.log gets everything (RunLog lowers the tambridge logger to INFO).
    root = logging.getLogger()
    if not any(getattr(handler, "tambridge_console", False) for handler in root.handlers):
        console = logging.StreamHandler()
        console.tambridge_console = True
        console.setLevel(logging.WARNING)
        console.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
        root.addHandler(console)


def _check_plot_and_json(plot: Path, json_path: Path | None, inputs: tuple) -> None:
    """The output checks of ``evaluate`` and ``compare``: a PNG ``plot`` and an optional ``json_path``, neither an
    input, one another, or a file a run wrote (its splats.ply, metrics.json...)."""
    from tambridge.files import check_output_file
    from tambridge.run_folder import check_not_a_runs_own_file

    check_output_file(plot, "--plot", inputs)
    if Path(plot).suffix.lower() != ".png":
        raise TambridgeError(f"--plot {plot}: the plot is a PNG; name the file *.png")
    check_not_a_runs_own_file(plot, "--plot")
    if json_path:
        check_output_file(json_path, "--json", inputs, (("--plot", plot),))
        check_not_a_runs_own_file(json_path, "--json")


def _print_run_summary(result) -> None:
    metrics = result.metrics
    if metrics.trajectory is not None:
        click.echo(
            f"ATE RMSE: {metrics.trajectory.ate_rmse_m * 100:.2f} cm over {metrics.trajectory.pose_count} poses "
            f"(SE(3)-aligned); RPE {metrics.trajectory.rpe_trans_rmse_m * 100:.2f} cm/frame"
        )
    # Lost frames keep a pose (bridged between tracked ones) and count in the ATE, as in any trajectory file.
    lost = f", {metrics.frames_lost} lost (run.log names them)" if metrics.frames_lost else ""
    click.echo(f"{metrics.frames} frames at {metrics.fps_end_to_end:.1f} frames/s{lost}")
    click.echo(f"outputs: {result.output_dir}")


def _run_options(function):
    for option in reversed(
        [
            click.option("-o", "--output", "output_dir", type=click.Path(), required=True, callback=_output_folder,
                         help="Output folder (new, empty, or of an earlier run given --overwrite or --resume)."),
            click.option("--config", "preset", type=click.Path(path_type=Path), help="YAML preset (configs/*.yaml)."),
            click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE", help="Override a config key, e.g. mapper.iterations=50."),
            click.option("--max-frames", type=int, help="Use at most this many frames."),
            click.option("--stride", type=int, help="Use every n-th frame."),
            click.option("--camera", "camera_file", type=click.Path(path_type=Path), help="camera.yaml for a non-TUM camera."),
            click.option("--quiet", is_flag=True, help="No progress bars."),
        ]
    ):
        function = option(function)
    return function


def _resolve_config(preset, overrides, max_frames, stride, camera_file):
    from tambridge.config import load_config

    extra = list(overrides)
    if max_frames is not None:
        extra.append(f"input.max_frames={max_frames}")
    if stride is not None:
        extra.append(f"input.stride={stride}")
    if camera_file is not None:
        extra.append(f"input.camera_file={camera_file}")
    return load_config(preset, extra)


@main.command()
@click.argument("sequence_dir", type=click.Path(path_type=Path))
@_run_options
@click.option("--viewer", metavar="rerun|rerun:FILE.rrd", help="Stream to a rerun viewer, or save a rerun recording.")
@click.option("--mesh-from", type=click.Choice([source.value for source in MeshSource]),
              help="Depth fused into mesh.ply: the sensor's (sensor, default) or rendered from the Gaussian map (rendered).")
@click.option("--resume", is_flag=True,
              help="Continue a killed run from OUTPUT/checkpoint/ (give the same sequence and options).")
@click.option("--overwrite", is_flag=True,
              help="Replace the run in OUTPUT: remove the files its manifest lists (and nothing else) first.")
@click.option("--device", type=click.Choice([device.value for device in Device]),
              help="Where the Gaussian map and the bridge run: cpu (default), cuda (needs a GPU and gsplat), auto.")
def reconstruct(sequence_dir, output_dir, preset, overrides, max_frames, stride, camera_file, quiet, viewer, mesh_from,
                resume, overwrite, device) -> None:
    """Track SEQUENCE_DIR (TUM layout) and write trajectory, splats, mesh and metrics to --output."""
    from pipelines.reconstruct import reconstruct as run
    from tambridge.run_folder import Start

    if resume and overwrite:
        raise click.UsageError("--resume continues the run in OUTPUT and --overwrite replaces it: give one of them")

    if mesh_from is not None:
        overrides = (*overrides, f"mesh.source={mesh_from}")
    if device is not None:
        overrides = (*overrides, f"device={device}")
    config = _resolve_config(preset, overrides, max_frames, stride, camera_file)
    start = Start.RESUME if resume else Start.OVERWRITE if overwrite else Start.NEW
    _print_run_summary(run(sequence_dir, output_dir, config, progress=not quiet, viewer=viewer, start=start))
    click.echo(f"report: {Path(output_dir) / 'report' / 'index.html'}")


@main.command()
@click.argument("sequences", nargs=-1, required=True)
@click.option("-o", "--output", "output_dir", type=click.Path(path_type=Path), required=True,
              help="Output folder: OUT/<sequence name>/ per sequence, and the batch's summary.")
@click.option("--config", "preset", type=click.Path(path_type=Path), help="YAML preset (configs/*.yaml).")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE", help="Override a config key, e.g. mapper.iterations=50.")
@click.option("--address", metavar="auto|HOST:PORT",
              help="A Ray cluster made with `ray start` (default: $RAY_ADDRESS, else a Ray on this machine).")
@click.option("--cpus-per-run", type=click.IntRange(min=1), default=1, show_default=True,
              help="CPUs Ray reserves for one sequence; its run's thread count.")
@click.option("--retries", type=click.IntRange(min=0), default=2, show_default=True,
              help="Attempts after the first for a sequence that fails (not for one whose input its run refused).")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def batch(sequences, output_dir, preset, overrides, address, cpus_per_run, retries, quiet) -> None:
    """Reconstruct many SEQUENCES (folders, glob patterns, or text files of one folder a line) on Ray.

    Each sequence is written to OUT/<name>/ as `reconstruct` would; frames are read by each worker from the path
    given, so on a cluster that path and OUT must be on a file system every node sees. Rerunning the command skips
    finished sequences and resumes killed ones from their checkpoint. Writes OUT/summary.json, OUT/summary.csv and
    OUT/index.html; exits 1 when a sequence failed, 130 when stopped with Ctrl-C.
    """
    from pipelines.batch import BatchOptions, run_batch
    from tambridge.batch.sequences import resolve_sequences
    from tambridge.batch.summary import counts

    options = BatchOptions(preset, tuple(overrides), address, cpus_per_run, retries)
    result = run_batch(resolve_sequences(sequences), output_dir, options, progress=not quiet)
    click.echo(", ".join(f"{count} {status}" for status, count in counts(result.rows).items() if count))
    click.echo(f"summary: {Path(output_dir) / 'index.html'}")
    if result.interrupted:
        click.echo("batch interrupted: run the same command again to go on (finished sequences are skipped)", err=True)
        sys.exit(130)
    for row in result.failed:
        click.echo(f"failed: {row.name}: {row.error}", err=True)
    if result.failed:
        click.echo(f"error: {len(result.failed)} of {len(result.rows)} sequences failed (see summary.json)", err=True)
        sys.exit(1)


@main.command("config")
@click.option("--config", "preset", type=click.Path(path_type=Path), help="YAML preset (configs/*.yaml).")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE", help="Override a config key, e.g. mapper.iterations=50.")
def show_config(preset, overrides) -> None:
    """Print the resolved config, one `key = value  # what it is; what it accepts` line per key."""
    from tambridge.config import describe_config, load_config

    for line in describe_config(load_config(preset, overrides)):
        click.echo(line)


@main.command()
@click.option("-o", "--output", "output_dir", type=click.Path(), default="out/demo", show_default=True, callback=_output_folder,
              help="Output folder; an earlier demo run in it is replaced.")
@click.option("--frames", type=click.IntRange(min=1), default=60, show_default=True)
@click.option("--size", default="320x240", show_default=True, help="WIDTHxHEIGHT of the synthetic images.")
@click.option("--config", "preset", type=click.Path(path_type=Path), help="YAML preset (configs/*.yaml).")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE")
def demo(output_dir, frames, size, preset, overrides) -> None:
    """Make a synthetic sequence with exact ground truth and reconstruct it: the quick check of an install."""
    from pipelines.reconstruct import reconstruct as run
    from tambridge.checkpoint import checkpoint_path
    from tambridge.evaluation.metrics import read_metrics
    from tambridge.io.synthetic import SynthOptions, write_synthetic_sequence
    from tambridge.run_folder import FINISHED_MARKER, Start, check_output_folder

    width, height = _parse_size(size)
    config = _resolve_config(preset, overrides, None, None, None)
    # Before rendering: a finished demo's run is replaced; anything else is treated as a new run treats it (a
    # finished or killed run of a sequence, or a folder of other files, is refused).
    finished = output_dir / FINISHED_MARKER
    earlier_demo = finished.is_file() and Path(read_metrics(finished).sequence).parent.name.startswith(DEMO_PREFIX)
    if finished.is_file() and not earlier_demo:
        raise TambridgeError(f"-o {output_dir}: holds a finished run that is not a demo's; give another -o (the demo "
                             "replaces only its own earlier run)")
    if checkpoint_path(output_dir).is_file():
        raise TambridgeError(f"-o {output_dir}: holds a killed run's checkpoint; give another -o (or continue that run "
                             "with tambridge reconstruct --resume)")
    start = Start.OVERWRITE if earlier_demo else Start.NEW
    check_output_folder(output_dir, start, [str(checkpoint_path(output_dir).relative_to(output_dir))])
    with tempfile.TemporaryDirectory(prefix=DEMO_PREFIX) as temp:
        sequence_dir = Path(temp) / "synthetic"
        click.echo(f"rendering a {frames}-frame {width}x{height} synthetic sequence ...")
        write_synthetic_sequence(sequence_dir, SynthOptions(frame_count=frames, width=width, height=height, seed=config.seed))
        # The demo is the install check a user repeats: it replaces its own earlier run (only the files it wrote).
        _print_run_summary(run(sequence_dir, output_dir, config, start=start))


DEMO_PREFIX = "tambridge-demo-"
"""The demo's temporary sequence folder starts so; a finished run's metrics.json names its sequence folder."""


MAX_SYNTHETIC_SIDE_PX = 4096
"""The longest side of a synthetic image: the renderer holds a frame's rays in memory (a 100000-pixel side would ask
for tens of GB)."""


def _parse_size(size: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in size.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"{size!r}: expected WIDTHxHEIGHT, e.g. 160x120", param_hint="--size") from None
    if width < 16 or height < 16:
        raise click.BadParameter(f"{size!r}: images must be at least 16x16", param_hint="--size")
    if width > MAX_SYNTHETIC_SIDE_PX or height > MAX_SYNTHETIC_SIDE_PX:
        raise click.BadParameter(f"{size!r}: images must be at most {MAX_SYNTHETIC_SIDE_PX}x{MAX_SYNTHETIC_SIDE_PX}",
                                 param_hint="--size")
    return width, height


@main.command()
@click.argument("output_dir", type=click.Path(path_type=Path))
@click.option("--frames", type=click.IntRange(min=1), default=30, show_default=True)
@click.option("--size", default="160x120", show_default=True, help="WIDTHxHEIGHT.")
@click.option("--depth-noise", type=click.FloatRange(min=0.0), default=0.0, help="Depth noise sigma at 1 m, metres (grows with z^2).")
@click.option("--colour-noise", type=click.FloatRange(min=0.0), default=0.0, help="Colour noise sigma, in [0, 1] units.")
@click.option("--motion-blur", "exposure", type=click.FloatRange(min=0.0), default=0.0, show_default=True, metavar="EXPOSURE_S",
              help="Exposure time, seconds (e.g. 0.033): each colour frame is the mean of sharp renders along the true "
                   "path over [t - EXPOSURE_S/2, t + EXPOSURE_S/2], and gt_rgb/ keeps the sharp frames; depth stays "
                   "sharp. 0: no blur. (Until this version the value was a count of sub-frames.)")
@click.option("--blur-subframes", type=click.IntRange(min=1), default=None,
              help="Sharp renders averaged per blurred frame (default: enough that the image moves at most half a "
                   "pixel between them).")
@click.option("--rotation-bursts", type=click.IntRange(min=0), default=0, show_default=True,
              help="Bursts of fast rotation (the camera tilts out and back), evenly spaced along the loop.")
@click.option("--burst-speed", type=click.FloatRange(min=0.0, min_open=True), default=90.0, show_default=True,
              help="Angular speed of the bursts, degrees per second.")
@click.option("--burst-duration", type=click.FloatRange(min=0.0, min_open=True), default=1.5, show_default=True,
              help="Length of each burst, seconds.")
@click.option("--supersampling", type=click.IntRange(min=1), default=1, show_default=True,
              help="Odd k: k x k rays per pixel averaged (anti-aliased colour, as a camera's pixel integrates); ~k^2 slower.")
@click.option("--colour-baseline", type=float, default=0.0, show_default=True,
              help="Metres between a separate colour camera and the depth camera (unregistered, Kinect v1 style; 0: registered).")
@click.option("--colour-focal-scale", type=click.FloatRange(min=0.0, min_open=True), default=1.0, show_default=True,
              help="The separate colour camera's focal length over the depth camera's (Kinect v1: about 0.9).")
@click.option("--depth-delay", type=float, default=0.0, show_default=True, metavar="SECONDS",
              help="Depth images taken this long after their colour images (negative: before), stamped and rendered "
                   "at that time, as a Kinect's two streams (TUM: -17 to +16 ms).")
@click.option("--rolling-shutter", type=click.FloatRange(min=0.0), default=0.0, show_default=True, metavar="READOUT_S",
              help="A rolling-shutter colour camera: rows read top to bottom over READOUT_S seconds, the middle row "
                   "at the stamp (written to camera.yaml as rolling_shutter_s); depth stays global. 0: global shutter.")
@click.option("--seed", type=int, default=0)
def synth(output_dir, frames, size, depth_noise, colour_noise, exposure, blur_subframes, rotation_bursts, burst_speed,
          burst_duration, supersampling, colour_baseline, colour_focal_scale, depth_delay, rolling_shutter, seed) -> None:
    """Write a synthetic TUM-layout sequence (textured room, closed loop) with exact ground truth."""
    from tambridge.files import check_new_or_empty_folder, staged_folder
    from tambridge.io.synthetic import RotationBursts, SynthOptions, write_synthetic_sequence

    width, height = _parse_size(size)
    # Frames of an earlier or longer sequence, or the user's files, would mix with the new ones.
    check_new_or_empty_folder(output_dir)
    if supersampling % 2 == 0:
        raise click.BadParameter(f"{supersampling}: must be odd (the centre ray gives the depth)", param_hint="--supersampling")
    options = SynthOptions(frames, width, height, depth_noise_m=depth_noise, colour_noise=colour_noise,
                           exposure_s=exposure, blur_subframes=blur_subframes,
                           bursts=RotationBursts(rotation_bursts, burst_speed, burst_duration),
                           supersampling=supersampling, seed=seed,
                           colour_baseline_m=colour_baseline, colour_focal_scale=colour_focal_scale,
                           depth_delay_s=depth_delay, rolling_shutter_s=rolling_shutter)
    # A stopped synth leaves no partial sequence.
    with staged_folder(output_dir) as staging:
        write_synthetic_sequence(staging, options)
    click.echo(f"wrote {frames} frames to {output_dir}")


@main.command()
@click.argument("folder", type=click.Path(path_type=Path))
@click.option("--rate", type=float, required=True, metavar="HZ",
              help="The camera's frames per second: frame i gets the timestamp i / HZ.")
@click.option("--depth-scale", type=float, default=None,
              help="Depth units per metre (1000 for millimetres), for the camera.yaml made from Open3D's "
                   "camera_intrinsic.json where the folder has one.")
def index(folder, rate, depth_scale) -> None:
    """Make FOLDER of colour and depth images (color/ and depth/, as Open3D's recorder writes them) a TUM-layout
    sequence: write its rgb.txt and depth.txt, pairing images by name, and camera.yaml from Open3D's intrinsics."""
    from tambridge.io.image_folders import write_tum_index

    images = write_tum_index(folder, rate, depth_scale)
    camera = f", camera.yaml from {images.open3d_intrinsic.name}" if images.camera_from_open3d else ""
    unpaired = f" ({len(images.rgb_only)} colour images without depth listed in rgb.txt only)" if images.rgb_only else ""
    click.echo(f"wrote rgb.txt and depth.txt of {len(images.rgb_names)} frames{unpaired}{camera} to {folder}")


@main.command()
@click.argument("estimate", type=click.Path(path_type=Path))
@click.argument("ground_truth", type=click.Path(path_type=Path))
@click.option("--align", type=click.Choice(["se3", "sim3", "none"]), default="se3", show_default=True)
@click.option("--plot", type=click.Path(path_type=Path), help="PNG to write (default: ESTIMATE with .png).")
@click.option("--json", "json_path", type=click.Path(path_type=Path), help="Write the metrics as JSON here.")
def evaluate(estimate, ground_truth, align, plot, json_path) -> None:
    """ATE and RPE of a TUM trajectory ESTIMATE against GROUND_TRUTH, with a plot."""
    from tambridge.evaluation.plots import plot_trajectory_errors
    from tambridge.evaluation.trajectory import evaluate_trajectory
    from tambridge.files import atomic_write_text
    from tambridge.run_folder import add_to_manifest
    from tambridge.trajectory import read_tum_trajectory

    if Path(estimate).resolve() == Path(ground_truth).resolve():
        raise TambridgeError(f"{estimate}: is both ESTIMATE and GROUND_TRUTH; give the estimate and the ground truth")
    plot = plot or Path(estimate).with_suffix(".png")
    _check_plot_and_json(plot, json_path, (estimate, ground_truth))
    try:
        errors = evaluate_trajectory(read_tum_trajectory(estimate), read_tum_trajectory(ground_truth), align)
    except ValueError as error:
        _fail(TambridgeError(f"{estimate}: {error}"))
    summary = errors.summary()
    rows = [
        ("poses", f"{errors.pose_count}"),
        ("alignment", align),
        ("ATE RMSE", f"{errors.ate_rmse_m * 100:.3f} cm"),
        ("ATE mean", f"{errors.ate_mean_m * 100:.3f} cm"),
        ("ATE median", f"{errors.ate_median_m * 100:.3f} cm"),
        ("ATE max", f"{errors.ate_max_m * 100:.3f} cm"),
        ("RPE trans RMSE", f"{errors.rpe_trans_rmse_m * 100:.3f} cm/frame"),
        ("RPE rot RMSE", f"{errors.rpe_rot_rmse_deg:.3f} deg/frame"),
        ("scale", f"{errors.scale:.4f}"),
    ]
    width = max(len(name) for name, _ in rows)
    for name, value in rows:
        click.echo(f"{name:<{width}}  {value}")
    plot_trajectory_errors({Path(estimate).stem: errors}, plot, title=str(estimate))
    click.echo(f"plot: {plot}")
    if json_path:
        atomic_write_text(json_path, json.dumps(summary, indent=2) + "\n")
    # Written into a run's folder (the default plot lies beside trajectory.txt): --overwrite removes them with the run.
    for written in filter(None, (plot, json_path)):
        add_to_manifest(Path(estimate).parent, written)


@main.command("export-mesh")
@click.argument("run_dir", type=click.Path(path_type=Path))
@click.option("--format", "mesh_format", type=click.Choice(["obj", "glb", "ply"]), default="obj", show_default=True)
@click.option("-o", "--output", "output_path", type=click.Path(path_type=Path), help="Default: RUN_DIR/mesh.FORMAT.")
def export_mesh(run_dir, mesh_format, output_path) -> None:
    """Convert RUN_DIR/mesh.ply (from reconstruct) to OBJ, GLB or PLY for other tools. OBJ and PLY keep the run's
    world (z up); GLB is turned to glTF's y up, as glTF viewers expect."""
    from tambridge.evaluation.metrics import read_metrics
    from tambridge.export.mesh import convert_mesh
    from tambridge.export.world import UpSource, gltf_from_world
    from tambridge.files import check_output_file
    from tambridge.run_folder import add_to_manifest, check_not_a_runs_own_file, is_listed

    output_path = output_path or Path(run_dir) / f"mesh.{mesh_format}"
    check_output_file(output_path, "-o", (Path(run_dir) / "mesh.ply",))
    check_not_a_runs_own_file(output_path, "-o")
    if output_path.exists() and not is_listed(run_dir, output_path):
        raise TambridgeError(f"-o {output_path}: exists and is not a file of the run in {run_dir}; remove it or name "
                             "a new file")
    if output_path.suffix.lower() != f".{mesh_format}":
        raise TambridgeError(f"-o {output_path}: --format {mesh_format} writes a .{mesh_format} file; name the file "
                             f"*.{mesh_format} or pick the format of its suffix")
    rotation = None
    if mesh_format == "glb":
        # glTF fixes y as up: the run's world (metrics.json says which) is turned into glTF's axes.
        world = read_metrics(Path(run_dir) / "metrics.json").world
        if world is None:
            raise TambridgeError(f"{Path(run_dir) / 'metrics.json'}: says nothing of the run's world, which a .glb "
                                 "needs (which way is up); run reconstruct again")
        rotation = gltf_from_world(UpSource(world.up_source))
    mesh = convert_mesh(Path(run_dir) / "mesh.ply", output_path, mesh_format, rotation)
    add_to_manifest(Path(run_dir), output_path)
    click.echo(f"wrote {output_path} ({len(mesh.vertices)} vertices, {len(mesh.faces)} triangles)")


@main.command("export")
@click.argument("run_dir", type=click.Path(path_type=Path))
@click.option("--format", "export_format", type=click.Choice(["colmap", "nerfstudio"]), required=True,
              help="colmap: sparse/0/ model and images/ (gsplat, INRIA 3DGS, COLMAP MVS); nerfstudio: transforms.json.")
@click.option("-o", "--output", "output_dir", type=click.Path(), callback=_output_folder,
              help="New or empty folder (default: RUN_DIR/export_FORMAT).")
@click.option("--frames", default="keyframes", show_default=True, metavar="keyframes|all|every:N",
              help="Which frames become images.")
@click.option("--images", type=click.Choice(["copy", "link", "undistort"]), default="copy", show_default=True,
              help="Copy or symlink the colour files (camera with their distortion), or write them undistorted as the "
                   "run saw them, cropped to the pixels with data around the principal point (pinhole; what "
                   "trainers without distortion need, e.g. for TUM fr1).")
@click.option("--text", is_flag=True, help="Also write COLMAP's .txt model files.")
def export(run_dir, export_format, output_dir, frames, images, text) -> None:
    """Export a finished reconstruct run (RUN_DIR) as a COLMAP model or nerfstudio data, for offline training."""
    from pipelines.export import export_run

    result = export_run(run_dir, output_dir, export_format, frames, images, text)
    tracks = f" ({result.observations} observations in their tracks)" if result.observations else ""
    if result.observations == 0:
        tracks = " (none with a track: a track needs a point seen in two images)"
    click.echo(f"wrote {result.images} images and {result.points} points{tracks} to {result.output_dir}")
    click.echo(f"points: {result.points_source}")


@main.command()
@click.argument("sequence_dir", type=click.Path(path_type=Path))
@click.option("-o", "--output", "output_dir", type=click.Path(), required=True, callback=_output_folder,
              help="Output folder.")
@click.option("--every", type=int, default=5, show_default=True, help="Use every n-th frame.")
@click.option("--max-frames", type=int, help="Use at most this many of those frames.")
@click.option("--camera", "camera_file", type=click.Path(path_type=Path), help="camera.yaml for a non-TUM camera.")
def colmap(sequence_dir, output_dir, every, max_frames, camera_file) -> None:
    """COLMAP (SIFT, sequential matching, incremental mapping) on SEQUENCE_DIR's colour images: a monocular baseline."""
    from pipelines.colmap import colmap as run

    if every < 1:
        raise click.BadParameter(f"--every {every}: must be at least 1")
    result = run(sequence_dir, output_dir, every=every, max_frames=max_frames, camera_file=camera_file)
    metrics = result.metrics
    click.echo(f"COLMAP registered {metrics['registered']} of {metrics['images']} images in {metrics['seconds']:.1f} s")
    if result.errors is not None:
        click.echo(f"ATE RMSE: {result.errors.ate_rmse_m * 100:.2f} cm over {result.errors.pose_count} poses "
                   f"(Sim(3)-aligned, scale {result.errors.scale:.4f})")
    click.echo(f"trajectory: {Path(output_dir) / 'trajectory.txt'}")


@main.command()
@click.argument("estimates", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--gt", "ground_truth", type=click.Path(path_type=Path), required=True, help="Ground-truth TUM file.")
@click.option("--sim3", "sim3_names", multiple=True, metavar="FILE",
              help="Align this one with Sim(3) (monocular); COLMAP files from 'tambridge colmap' are found by themselves.")
@click.option("--plot", type=click.Path(path_type=Path), default=Path("compare.png"), show_default=True)
@click.option("--json", "json_path", type=click.Path(path_type=Path), help="Write the table as JSON here.")
def compare(estimates, ground_truth, sim3_names, plot, json_path) -> None:
    """ATE/RPE of several TUM trajectories ESTIMATES against --gt in one table, and one plot of all."""
    from pipelines.compare import compare_files
    from tambridge.files import atomic_write_text

    _check_plot_and_json(plot, json_path, (*estimates, ground_truth))
    comparison = compare_files(ground_truth, estimates, sim3_names, plot)
    click.echo(comparison.table())
    click.echo(f"plot: {plot}")
    if json_path:
        atomic_write_text(json_path, json.dumps(comparison.rows(), indent=2) + "\n")


@main.command()
@click.argument("run_dir", type=click.Path(path_type=Path))
def report(run_dir) -> None:
    """Rebuild RUN_DIR/report/index.html from a finished run (adds RUN_DIR/colmap/trajectory.txt when present)."""
    from tambridge.evaluation.report import report_from_run

    click.echo(f"report: {report_from_run(run_dir)}")


@main.command()
@click.argument("run_dir", type=click.Path(path_type=Path))
@click.option("--port", type=click.IntRange(0, 65535), default=0, show_default=True,
              help="Port on 127.0.0.1 (0: a free one).")
def view(run_dir, port) -> None:
    """Serve RUN_DIR's interactive splat viewer (report/viewer/) at http://127.0.0.1:PORT until Ctrl-C or SIGTERM."""
    from pipelines.view import ViewerServer

    with ViewerServer(run_dir, port) as server:
        click.echo(f"viewer: {server.url}")
        click.echo("serving on 127.0.0.1 only; Ctrl-C to stop")
        server.serve_until_stopped()
        click.echo("stopped")


@main.command()
@click.argument("name")
@click.option("--to", "destination", type=click.Path(path_type=Path), default=Path("data"), show_default=True)
@click.option("--base-url", default=None, help="Mirror of the TUM dataset folder (default: the TUM site).")
def download(name, destination, base_url) -> None:
    """Download and unpack a TUM RGB-D sequence, e.g. fr1/desk (needs internet)."""
    from tambridge.io.download import TUM_BASE_URL, download_tum

    folder = download_tum(name, destination, base_url or TUM_BASE_URL)
    click.echo(f"sequence ready: {folder}")
    click.echo(f"run: tambridge reconstruct {folder} -o out/{folder.name}")


if __name__ == "__main__":
    main()
