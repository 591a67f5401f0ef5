"""The run report: ``report/index.html`` with matplotlib PNGs beside it, readable from ``file://`` with no server.

Sections appear only when their data exists: trajectory against ground truth (top view and ATE over time with
the worst 2-second segment shaded and named, COLMAP's Sim(3)-aligned path too when given), renders beside input
frames, the map as exported (scores and novel views as a viewer shows splats.ply), an interactive viewer of
splats.ply (``viewer/``, :mod:`tambridge.export.web_viewer`), time per stage,
Gaussian count over time, and the metrics table (every scalar of ``metrics.json``). Images are linked by relative paths,
so the folder can be moved or zipped as a whole. Every file is written atomically.
"""

from __future__ import annotations

import dataclasses
import datetime
import html
import json
import logging
from pathlib import Path
from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import yaml  # noqa: E402

from tambridge.camera import Camera, find_sensor  # noqa: E402
from tambridge.errors import TambridgeError  # noqa: E402
from tambridge.state import dotted_items  # noqa: E402
from tambridge.evaluation.colmap import is_monocular_trajectory_file  # noqa: E402
from tambridge.evaluation.exported import ExportedMap  # noqa: E402
from tambridge.evaluation.metrics import RunMetrics, metrics_json, read_metrics  # noqa: E402
from tambridge.evaluation.plots import plot_trajectory_errors  # noqa: E402
from tambridge.evaluation.trajectory import (  # noqa: E402
    WORST_WINDOW_S, TrajectoryErrors, TrajectoryEvaluationError, evaluate_trajectory, worst_error_window,
)
from tambridge.export.web_viewer import DATA_NAME, RUN_VIEWER_FOLDER, VIEWER_FILES, read_viewer_view, write_run_viewer  # noqa: E402
from tambridge.files import atomic_path, atomic_write_text  # noqa: E402
from tambridge.images import rgb_uint8  # noqa: E402
from tambridge.io.tum import RgbdSequence  # noqa: E402
from tambridge.mapping.stage import MappingStage  # noqa: E402
from tambridge.trajectory import Trajectory, read_tum_trajectory  # noqa: E402

logger = logging.getLogger("tambridge.evaluation.report")

MAX_RENDER_ROWS = 6
EXPORTED_DIFFERENCE_RANGE = 0.3
"""The difference image of the "As exported" section spans -0.3 to 0.3 (colours in [0, 1])."""


@dataclasses.dataclass
class RenderPair:
    """An input frame and the map's render of the same view, both (H, W, 3) uint8; ``label`` names the view."""

    label: str
    input_rgb: np.ndarray
    rendered_rgb: np.ndarray


REPORT_FILES = ("index.html", "trajectory.png", "renders.png", "exported.png", "stages.png", "gaussians.png",
                *(f"{RUN_VIEWER_FOLDER.name}/{name}" for name in VIEWER_FILES))
"""Every file :func:`write_report` may write into the report folder."""


def write_report(
    report_dir: Path,
    metrics: RunMetrics,
    trajectory_errors: dict[str, TrajectoryErrors] | None = None,
    render_pairs: Sequence[RenderPair] = (),
    gaussian_counts: tuple[np.ndarray, np.ndarray] | None = None,
    title: str = "tambridge run",
    web_viewer: bool = False,
    exported_pairs: Sequence[RenderPair] = (),
    keep_figures: bool = False,
) -> Path:
    """Write ``report_dir/index.html`` and its PNGs; returns the HTML path.

    ``metrics``: the run's metrics (as written to metrics.json). ``trajectory_errors``: name -> errors of
    each estimate against the same ground truth (e.g. the run's SE(3)-aligned trajectory and COLMAP's Sim(3)
    one). ``render_pairs``: at most :data:`MAX_RENDER_ROWS` are shown, evenly spread. ``gaussian_counts``:
    frame indices (N,) and the map's Gaussian count after each (N,). ``web_viewer``: embed ``report_dir/viewer/``
    (written by :func:`~tambridge.export.web_viewer.write_run_viewer`). ``exported_pairs``: novel views' frames
    beside splats.ply rendered as exported (:func:`exported_section`). ``keep_figures``: where renders, exported
    renders or the Gaussian count are not given, show the figures an earlier write left in ``report_dir`` (a report
    rebuilt after the run, whose renders lived only during it).
    """
    report_dir = Path(report_dir)
    report_dir.mkdir(parents=True, exist_ok=True)
    sections = []
    if trajectory_errors:
        plot_trajectory_errors(trajectory_errors, report_dir / "trajectory.png", title="aligned to ground truth")
        rows = "".join(
            f"<tr><td>{html.escape(name)}</td><td>{errors.alignment}</td><td>{errors.pose_count}</td>"
            f"<td>{errors.ate_rmse_m * 100:.2f}</td><td>{errors.rpe_trans_rmse_m * 100:.2f}</td></tr>"
            for name, errors in trajectory_errors.items()
        )
        sections.append(
            "<h2>Trajectory</h2>"
            '<p>Left: top view of each estimate after alignment, ground truth dashed. Right: absolute trajectory '
            "error over time.</p>"
            '<img src="trajectory.png" alt="trajectory top view and ATE over time">' + _worst_segments(trajectory_errors) +
            '<table class="small"><tr><th>trajectory</th><th>alignment</th><th>poses</th><th>ATE RMSE [cm]</th>'
            f"<th>RPE [cm/frame]</th></tr>{rows}</table>"
        )
    if render_pairs:
        _plot_render_grid(render_pairs, report_dir / "renders.png")
    if render_pairs or (keep_figures and (report_dir / "renders.png").is_file()):
        sections.append(
            "<h2>Renders</h2><p>Input frames (left) beside the Gaussian map rendered at their poses (right).</p>"
            '<img src="renders.png" alt="renders beside input frames">'
        )
    if metrics.map is not None or exported_pairs:
        sections.append(exported_section(metrics, exported_pairs, report_dir / "exported.png", keep_figures))
    if web_viewer:
        sections.append(_web_viewer_section())
    if metrics.seconds_per_stage:
        _plot_stage_seconds(metrics.seconds_per_stage, metrics.frontend_seconds_per_stage, report_dir / "stages.png")
        sections.append('<h2>Time per stage</h2><img src="stages.png" alt="seconds per stage">')
    counted = gaussian_counts is not None and len(gaussian_counts[0]) > 0
    if counted:
        _plot_gaussian_counts(*gaussian_counts, report_dir / "gaussians.png")
    if counted or (keep_figures and (report_dir / "gaussians.png").is_file()):
        sections.append('<h2>Gaussians</h2><img src="gaussians.png" alt="Gaussian count over time">')
    sections.append("<h2>Metrics</h2>" + _metrics_table(metrics_json(metrics)))
    generated = datetime.datetime.now().isoformat(timespec="seconds")
    page = _PAGE.format(title=html.escape(title), generated=generated, body="\n".join(sections))
    index = report_dir / "index.html"
    atomic_write_text(index, page)
    logger.info("report: %s", index)
    return index


def _worst_segments(trajectory_errors: dict[str, TrajectoryErrors]) -> str:
    """A paragraph naming each estimate's worst :data:`WORST_WINDOW_S`-second window (shaded in the plot for the
    first): its poses, its times from the estimate's first pose and its RMSE."""
    lines = "".join(
        f"<li>{html.escape(name)}: "
        f"{worst_error_window(errors.timestamps_s, errors.ate_errors_m).describe(errors.timestamps_s[0])}</li>"
        for name, errors in trajectory_errors.items()
    )
    return f'<p>Worst {WORST_WINDOW_S:g}-second segment (highest ATE RMSE):</p><ul class="worst">{lines}</ul>'


def report_from_run(run_dir: Path) -> Path:
    """Rebuild ``run_dir/report`` from a finished run's files (the renders' figures as the run left them: the renders
    themselves lived only during the run).

    Reads ``metrics.json`` and ``trajectory.txt``; the ground truth is the sequence's ``groundtruth.txt``; a
    COLMAP trajectory is added when ``run_dir/colmap/trajectory.txt`` exists (``tambridge colmap SEQ -o
    RUN_DIR/colmap``). A run's viewer is written again from ``splats.ply`` as it is now (left out, with a warning,
    where it is gone), from the first view the run gave it (:func:`viewer_camera_of_run`).
    """
    run_dir = Path(run_dir)
    metrics = read_metrics(run_dir / "metrics.json")
    errors = {}
    ground_truth_path = Path(metrics.sequence) / "groundtruth.txt"
    if ground_truth_path.is_file():
        ground_truth = read_tum_trajectory(ground_truth_path)
        estimates = {"tambridge (SE(3))": (run_dir / "trajectory.txt", "se3")}
        colmap_path = run_dir / "colmap" / "trajectory.txt"
        if colmap_path.is_file():
            align = "sim3" if is_monocular_trajectory_file(colmap_path) else "se3"
            estimates[f"COLMAP ({'Sim(3)' if align == 'sim3' else 'SE(3)'})"] = (colmap_path, align)
        for name, (path, align) in estimates.items():
            try:
                errors[name] = evaluate_trajectory(read_tum_trajectory(path), ground_truth, align)
            except TrajectoryEvaluationError as error:
                # As the run itself did (metrics.json trajectory_unavailable): the report goes without that ATE.
                logger.warning("%s: no ATE against %s: %s", path, ground_truth_path, error)
    if metrics.trajectory is not None and not ground_truth_path.is_file():
        logger.warning("%s: not found (the sequence moved?): the rebuilt report has no trajectory section; "
                       "metrics.json keeps the run's ATE", ground_truth_path)
    web_viewer = False
    if (run_dir / "splats.ply").is_file():
        # splats.ply as it is now (cleaned in another tool, say), from the first view the run gave the viewer.
        camera = viewer_camera_of_run(run_dir, Path(metrics.sequence))
        if camera is not None:
            write_run_viewer(run_dir, camera)
            web_viewer = True
        if not (run_dir / "report" / "renders.png").is_file():
            logger.warning("%s: gone: the renders lived only during the run, so the rebuilt report has none "
                           "(reconstruct again for them)", run_dir / "report" / "renders.png")
    elif metrics.map is not None or (run_dir / RUN_VIEWER_FOLDER / "index.html").is_file():
        logger.warning("%s: not found: the rebuilt report has no viewer", run_dir / "splats.ply")
    return write_report(run_dir / "report", metrics, errors, title=f"tambridge: {metrics.sequence}",
                        web_viewer=web_viewer, keep_figures=True)


def viewer_camera_of_run(run_dir: Path, sequence: Path) -> Camera | None:
    """The camera the run's viewer starts with: read back from the viewer the run wrote, else the frames' camera as
    the run read them from its ``sequence`` folder (config.yaml's camera file, the folder's own, or the TUM preset);
    None, with a warning, where neither can be read."""
    if (run_dir / RUN_VIEWER_FOLDER / DATA_NAME).is_file():
        return read_viewer_view(run_dir / RUN_VIEWER_FOLDER)[0]
    try:
        # The one key of config.yaml needed here, read as YAML: the config layer lies above this one.
        camera_file = yaml.safe_load((run_dir / "config.yaml").read_text())["input"]["camera_file"]
        return find_sensor(sequence, None if camera_file is None else Path(camera_file)).camera.undistorted()
    except (TambridgeError, OSError, yaml.YAMLError, KeyError, TypeError) as error:
        logger.warning("the rebuilt report has no viewer: the frames' camera could not be read (%s)", error)
        return None


def format_metric(value: object) -> str:
    """How a metric value is shown: floats with 6 significant digits, None as a dash, lists as JSON."""
    if value is None:
        return "-"
    if isinstance(value, (bool, int, str)):
        return str(value)
    if isinstance(value, float):
        return f"{value:.6g}"
    return json.dumps(value)


def _metrics_table(metrics: dict) -> str:
    rows = "".join(
        f'<tr><td>{html.escape(name)}</td><td class="value" data-key="{html.escape(name)}">'
        f"{html.escape(format_metric(value))}</td></tr>"
        for name, value in dotted_items(metrics).items()
    )
    return f'<table id="metrics"><tr><th>metric</th><th>value</th></tr>{rows}</table>'


def _web_viewer_section() -> str:
    """The interactive viewer of splats.ply, embedded and linked (it opens from file:// as from a server)."""
    viewer = f"{RUN_VIEWER_FOLDER.name}/index.html"
    return (
        "<h2>Splats</h2><p>splats.ply as any 3DGS viewer shows it (no per-view exposure), from the first frame's "
        "camera: drag to orbit, arrow keys to move, 0 to come back. "
        f'<a href="{viewer}">Open it in its own window</a>, or serve it with <code>tambridge view RUN</code>.</p>'
        f'<iframe id="web-viewer" src="{viewer}" title="splats.ply viewer" loading="lazy" '
        'style="display: block; box-sizing: border-box; width: 100%; aspect-ratio: 4 / 3; border: 1px solid #ddd;"></iframe>'
    )
def exported_section(metrics: RunMetrics, pairs: Sequence[RenderPair], path: Path, keep_figure: bool = False) -> str:
    """The "As exported" section: novel-view scores through the views' exposures beside those of splats.ply as a
    viewer shows it, and (when ``pairs`` are given, written to ``path``; with ``keep_figure``, the figure already at
    ``path``) input frame, render as exported and their difference for a few novel views."""
    rows = ""
    if metrics.map is not None:
        rendering = metrics.map.rendering
        for name, scores in (("through each view's exposure (the run's own)", rendering.novel_views),
                             ("as exported (splats.ply, no exposure, trajectory.txt's poses)", rendering.novel_views_exported)):
            rows += (f"<tr><td>{html.escape(name)}</td><td>{format_metric(scores.psnr_db)}</td>"
                     f"<td>{format_metric(scores.ssim)}</td></tr>")
    table = f'<table class="small"><tr><th>novel views</th><th>PSNR [dB]</th><th>SSIM</th></tr>{rows}</table>' if rows else ""
    figure = ""
    if pairs:
        _plot_exported_pairs(pairs, path)
    if pairs or (keep_figure and path.is_file()):
        figure = ('<p>Input frame, splats.ply rendered as exported at its pose, and their difference in brightness '
                  '(red: the render is brighter).</p>'
                  f'<img src="{path.name}" alt="input frames, renders as exported and their difference">')
    return "<h2>As exported</h2>" + table + figure


def _plot_exported_pairs(pairs: Sequence[RenderPair], path: Path) -> None:
    figure, axes = plt.subplots(len(pairs), 3, figsize=(12, 3 * len(pairs)), squeeze=False)
    for row, pair in zip(axes, pairs):
        difference = (pair.rendered_rgb.astype(np.float32) - pair.input_rgb.astype(np.float32)).mean(axis=2) / 255.0
        row[0].imshow(pair.input_rgb)
        row[1].imshow(pair.rendered_rgb)
        shown = row[2].imshow(difference, cmap="RdBu_r", vmin=-EXPORTED_DIFFERENCE_RANGE, vmax=EXPORTED_DIFFERENCE_RANGE)
        figure.colorbar(shown, ax=row[2], fraction=0.035)
        for axis, kind in zip(row, ("input", "as exported", "render - input")):
            axis.set_title(f"{pair.label}: {kind}", fontsize=9)
            axis.axis("off")
    _save(figure, path)


def _save(figure, path: Path) -> None:
    figure.tight_layout()
    with atomic_path(path) as temp_path:
        figure.savefig(temp_path, format="png", dpi=90)
    plt.close(figure)


def _plot_render_grid(pairs: Sequence[RenderPair], path: Path) -> None:
    chosen = [pairs[i] for i in np.unique(np.linspace(0, len(pairs) - 1, min(len(pairs), MAX_RENDER_ROWS)).astype(int))]
    figure, axes = plt.subplots(len(chosen), 2, figsize=(8, 3 * len(chosen)), squeeze=False)
    for row, pair in zip(axes, chosen):
        for axis, image, kind in ((row[0], pair.input_rgb, "input"), (row[1], pair.rendered_rgb, "render")):
            axis.imshow(image)
            axis.set_title(f"{pair.label}: {kind}", fontsize=9)
            axis.axis("off")
    _save(figure, path)


def _plot_stage_seconds(stage_seconds: dict, frontend_seconds: dict, path: Path) -> None:
    panels = [("pipeline stages", stage_seconds)] + ([("frontend stages", frontend_seconds)] if frontend_seconds else [])
    figure, axes = plt.subplots(1, len(panels), figsize=(6 * len(panels), 3.5), squeeze=False)
    for axis, (title, seconds) in zip(axes[0], panels):
        names = list(seconds)
        axis.barh(names, [seconds[name] for name in names], color="tab:blue")
        axis.invert_yaxis()
        axis.set_xlabel("seconds")
        axis.set_title(title)
    _save(figure, path)


def _plot_gaussian_counts(frame_indices: np.ndarray, counts: np.ndarray, path: Path) -> None:
    figure, axis = plt.subplots(figsize=(7, 3.5))
    axis.plot(np.asarray(frame_indices), np.asarray(counts), color="tab:green")
    axis.set_xlabel("frame")
    axis.set_ylabel("Gaussians")
    axis.set_title("Gaussian count over time")
    _save(figure, path)


_PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>{title}</title>
<style>
body {{ font-family: sans-serif; max-width: 1100px; margin: 2em auto; color: #222; }}
img {{ max-width: 100%; border: 1px solid #ddd; }}
table {{ border-collapse: collapse; margin: 1em 0; }}
td, th {{ border: 1px solid #ccc; padding: 0.2em 0.6em; text-align: left; font-size: 0.9em; }}
td.value {{ font-family: monospace; }}
</style>
</head>
<body>
<h1>{title}</h1>
<p>Generated {generated} by tambridge.</p>
{body}
</body>
</html>
"""


REPORT_RENDERS = 4
"""Frames rendered from the map for the report's grid (at the mapping resolution: cheap)."""
REPORT_EXPORTED_VIEWS = 3
"""Novel views rendered as exported for the report (at full resolution, as a viewer shows them)."""


def write_run_report(output_dir: Path, metrics: RunMetrics, sequence: RgbdSequence, errors: TrajectoryErrors | None,
                     mapping: MappingStage | None, exported: ExportedMap | None, trajectory: Trajectory,
                     gaussian_counts: list[tuple[int, int]]) -> None:
    """``output_dir/report/index.html``; adds COLMAP when ``output_dir/colmap/trajectory.txt`` exists.
    ``exported``: ``output_dir``'s splats.ply and trajectory.txt read back (None exactly when ``mapping`` is)."""
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
            pairs.append(RenderPair(f"frame {index}", rgb_uint8(mapping.images(int(index)).rgb.cpu().numpy()), rgb_uint8(rendered)))
    counts = np.array(gaussian_counts).reshape(-1, 2)
    # The viewer reads splats.ply and trajectory.txt as written, so it shows the world the user's files are in.
    web_viewer = mapping is not None and (output_dir / "splats.ply").is_file()
    if web_viewer:
        write_run_viewer(output_dir, sequence.camera)
    write_report(output_dir / "report", metrics, trajectory_errors, pairs,
                 (counts[:, 0], counts[:, 1]) if len(counts) else None, title=f"tambridge: {metrics.sequence}",
                 web_viewer=web_viewer,
                 exported_pairs=exported_pairs(exported, sequence, mapping) if mapping is not None else ())


def exported_pairs(exported: ExportedMap, sequence: RgbdSequence, mapping: MappingStage) -> list[RenderPair]:
    """:data:`REPORT_EXPORTED_VIEWS` novel views (frames that are no mapping view, evenly spread): the input frame
    beside ``exported`` rendered at its trajectory.txt pose, at full resolution."""
    view_frames = {view.frame_index for view in mapping.views}
    novel = [index for index in range(len(sequence)) if index not in view_frames]
    if not novel:
        return []
    chosen = [novel[i] for i in np.unique(np.linspace(0, len(novel) - 1, REPORT_EXPORTED_VIEWS).astype(int))]
    with mapping.threads():
        return [RenderPair(f"frame {index}", sequence[index].rgb,
                           rgb_uint8(exported.render(sequence.camera, index).rgb.clamp(0.0, 1.0).cpu().numpy()))
                for index in chosen]
