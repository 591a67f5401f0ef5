"""The README's picture from a finished run: an input frame, the Gaussian map rendered at that frame's pose, and
the trajectory against ground truth.

    python benchmarks/readme_figure.py RUN_DIR docs/images/overview.png [--frame N] [--sequence DIR]

RUN_DIR is an output folder of ``tambridge reconstruct`` on a sequence with ``groundtruth.txt``; the sequence is
the one its metrics.json names (relative paths are taken from the working directory) unless ``--sequence`` gives
it. The frame is rendered at full resolution from ``splats.ply`` at its pose in ``trajectory.txt``; by default it
is the frame halfway between the two middle keyframes, which no mapping view saw from there.
"""

from __future__ import annotations

import argparse
import io
import json
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from PIL import Image  # noqa: E402

from tambridge.evaluation.plots import plot_trajectory_errors  # noqa: E402
from tambridge.evaluation.trajectory import evaluate_trajectory  # noqa: E402
from tambridge.export.splats import load_ply  # noqa: E402
from tambridge.gaussians.rasterizer import render  # noqa: E402
from tambridge.io.tum import open_sequence  # noqa: E402
from tambridge.trajectory import read_tum_trajectory  # noqa: E402

FIGURE_WIDTH_IN = 10.0
DPI = 100
PALETTE_COLOURS = 256  # a palette PNG keeps the picture small enough for a README


def default_frame(trajectory_timestamps_s: np.ndarray, keyframe_timestamps_s: np.ndarray) -> int:
    """Index into the trajectory of the frame halfway between the two middle keyframes (a novel view)."""
    if len(keyframe_timestamps_s) < 2:
        return len(trajectory_timestamps_s) // 2
    keyframe_indices = np.searchsorted(trajectory_timestamps_s, keyframe_timestamps_s)
    middle = len(keyframe_indices) // 2
    return int((keyframe_indices[middle - 1] + keyframe_indices[middle]) // 2)


def make_figure(run_dir: Path, output_path: Path, frame: int | None, sequence_dir: Path | None) -> None:
    """Write the picture of ``run_dir`` to ``output_path`` (PNG)."""
    metrics = json.loads((run_dir / "metrics.json").read_text())
    sequence = open_sequence(sequence_dir or Path(metrics["sequence"]), check_depth_scale=False)
    if sequence.ground_truth is None:
        raise SystemExit(f"{sequence.folder}: no groundtruth.txt; the picture plots the trajectory against it")
    trajectory = read_tum_trajectory(run_dir / "trajectory.txt")
    keyframes = read_tum_trajectory(run_dir / "keyframes.txt")
    index = default_frame(trajectory.timestamps_s, keyframes.timestamps_s) if frame is None else frame
    stamp = trajectory.timestamps_s[index]
    frame_index = int(np.argmin(np.abs(sequence.timestamps_s - stamp)))
    observed = sequence[frame_index].rgb
    rendered = render(load_ply(run_dir / "splats.ply"), sequence.camera, trajectory.world_from_camera[index]).rgb
    rendered = (rendered.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
    # Undistortion leaves a border without data; show the region the evaluation scores.
    top, bottom, left, right = sequence.valid_region
    observed, rendered = observed[top:bottom, left:right], rendered[top:bottom, left:right]

    errors = evaluate_trajectory(trajectory, sequence.ground_truth, "se3")
    with tempfile.TemporaryDirectory() as temp:
        plot_path = Path(temp) / "trajectory.png"
        plot_trajectory_errors({"tambridge": errors}, plot_path)
        trajectory_plot = np.asarray(Image.open(plot_path).convert("RGB"))

    image_aspect = observed.shape[0] / observed.shape[1]
    plot_aspect = trajectory_plot.shape[0] / trajectory_plot.shape[1]
    top_height = FIGURE_WIDTH_IN / 2 * image_aspect
    bottom_height = FIGURE_WIDTH_IN * plot_aspect
    figure = plt.figure(figsize=(FIGURE_WIDTH_IN, top_height + bottom_height + 0.3))
    grid = figure.add_gridspec(2, 2, height_ratios=[top_height + 0.3, bottom_height], hspace=0.03, wspace=0.02,
                               left=0.005, right=0.995, top=0.97, bottom=0.005)
    name = sequence.folder.name
    titles = (f"input: {name}, frame {frame_index}", "render of splats.ply at its estimated pose (not a mapping view)")
    for column, (image, title) in enumerate(zip((observed, rendered), titles)):
        axis = figure.add_subplot(grid[0, column])
        axis.imshow(image)
        axis.set_title(title, fontsize=9)
        axis.axis("off")
    axis = figure.add_subplot(grid[1, :])
    axis.imshow(trajectory_plot)
    axis.axis("off")
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=DPI)
    plt.close(figure)
    picture = Image.open(buffer).convert("RGB").quantize(PALETTE_COLOURS, method=Image.Quantize.MEDIANCUT)
    output_path.parent.mkdir(parents=True, exist_ok=True)
    picture.save(output_path, optimize=True)
    print(f"wrote {output_path} ({output_path.stat().st_size // 1024} KB): frame {frame_index}, "
          f"ATE {errors.ate_rmse_m * 100:.2f} cm over {errors.pose_count} poses")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path, help="output folder of tambridge reconstruct")
    parser.add_argument("output", type=Path, help="PNG to write")
    parser.add_argument("--frame", type=int, help="index into trajectory.txt of the frame to show")
    parser.add_argument("--sequence", type=Path, help="the run's sequence folder (default: metrics.json's)")
    arguments = parser.parse_args()
    make_figure(arguments.run_dir, arguments.output, arguments.frame, arguments.sequence)


if __name__ == "__main__":
    main()
