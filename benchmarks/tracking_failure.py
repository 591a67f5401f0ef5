"""Sensor failures on real data: frames of all-invalid depth and black colour (a covered lens) mid-sequence.

    python benchmarks/tracking_failure.py                 # 7-Scenes, first 200 frames, 10 + 10 damaged frames
    python benchmarks/tracking_failure.py --frames 300 --no-depth 100-109 --black 200-209

The first ``--frames`` frames are copied to a temporary folder twice, one copy left as it is and one with the depth
of ``--no-depth`` set to 0 and the colour of ``--black`` to black (:func:`~tambridge.io.synthetic.blank_frames`).
Each copy is reconstructed (default preset, ``--set mapper.enabled=false --set mesh.enabled=false``) in its own
process. The table gives the counts metrics.json reports (``tracked by depth``: frames ORB could not place that
the depth term alone did, ``frontend.orb.depth_only_tracking``), the ATE (SE(3)-aligned) over the undamaged frames
and over the undamaged frames after the last damaged one, and the position error of the black frames within the
whole trajectory's alignment, for both runs. ``--extra`` passes reconstruct options to both (``--set
frontend.orb.depth_only_tracking=false``: black frames are lost, as before that setting). Writes
benchmarks/results/tracking_failure.json.
"""

from __future__ import annotations

import argparse
import datetime
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import describe_machine  # noqa: E402
from tambridge.evaluation.metrics import RunMetrics, read_metrics  # noqa: E402
from tambridge.evaluation.trajectory import evaluate_trajectory  # noqa: E402
from tambridge.files import atomic_write_text  # noqa: E402
from tambridge.io.synthetic import blank_frames  # noqa: E402
from tambridge.io.tum import read_file_list  # noqa: E402
from tambridge.trajectory import Trajectory, read_tum_trajectory  # noqa: E402

DEFAULT_SEQUENCE = ROOT.parent / "shared" / "data" / "7scenes_redkitchen_0-699"
RUN_OPTIONS = ("--set", "mapper.enabled=false", "--set", "mesh.enabled=false")


def frame_range(text: str) -> list[int]:
    """``"40-49"`` -> [40, ..., 49]; ``"3,7"`` -> [3, 7]."""
    frames = []
    for part in text.split(","):
        first, _, last = part.partition("-")
        frames += list(range(int(first), int(last or first) + 1))
    return frames


def copy_first_frames(source: Path, destination: Path, frames: int) -> None:
    """The first ``frames`` entries of rgb.txt and depth.txt with their images, ground truth and camera files."""
    destination.mkdir(parents=True)
    for listing in ("rgb.txt", "depth.txt"):
        entries = read_file_list(source / listing)[:frames]
        (destination / listing).write_text("".join(f"{stamp:.6f} {name}\n" for stamp, name in entries))
        for _, name in entries:
            (destination / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(source / name, destination / name)
    for extra in ("groundtruth.txt", "camera.txt", "camera.yaml"):
        if (source / extra).is_file():
            shutil.copyfile(source / extra, destination / extra)


def run(sequence: Path, out: Path, extra: list[str]) -> tuple[RunMetrics, float]:
    """Reconstruct ``sequence`` into ``out`` in a child process; returns its metrics.json and the wall seconds."""
    command = [sys.executable, str(ROOT / "cli.py"), "reconstruct", str(sequence), "-o", str(out), "--quiet",
               *RUN_OPTIONS, *extra]
    started = time.perf_counter()
    with open(out.parent / f"{out.name}.log", "w") as log:
        subprocess.run(command, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, check=True)
    return read_metrics(out / "metrics.json"), time.perf_counter() - started


def ate_cm(trajectory: Trajectory, ground_truth: Trajectory, frames: np.ndarray) -> float:
    """ATE RMSE (cm, SE(3)-aligned on these frames) of ``trajectory`` over the frame indices ``frames``."""
    subset = Trajectory(trajectory.timestamps_s[frames], trajectory.world_from_camera[frames])
    return evaluate_trajectory(subset, ground_truth).ate_rmse_m * 100.0


def black_frames_rmse_cm(trajectory: Trajectory, ground_truth: Trajectory, frames: list[int]) -> float | None:
    """RMS position error (cm) of the frames ``frames`` with the whole trajectory SE(3)-aligned (a lost frame keeps
    its constant-velocity prediction); None without such frames."""
    if not frames:
        return None
    errors = evaluate_trajectory(trajectory, ground_truth)
    chosen = np.isin(errors.timestamps_s, trajectory.timestamps_s[frames])
    return float(np.sqrt(np.mean(errors.ate_errors_m[chosen] ** 2)) * 100.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sequence", type=Path, default=DEFAULT_SEQUENCE)
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--no-depth", type=frame_range, default=frame_range("60-69"), help="frames whose depth is zeroed")
    parser.add_argument("--black", type=frame_range, default=frame_range("130-139"), help="frames made black")
    parser.add_argument("--extra", nargs=argparse.REMAINDER, default=[], help="further reconstruct options")
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks" / "results" / "tracking_failure.json")
    arguments = parser.parse_args()
    damaged_frames = sorted(set(arguments.no_depth) | set(arguments.black))
    if damaged_frames and damaged_frames[-1] >= arguments.frames:
        parser.error(f"damaged frame {damaged_frames[-1]} is beyond --frames {arguments.frames}")
    ground_truth = read_tum_trajectory(arguments.sequence / "groundtruth.txt")
    rows = []
    with tempfile.TemporaryDirectory(prefix="tambridge-failure-") as temp:
        clean, damaged = Path(temp) / "clean", Path(temp) / "damaged"
        copy_first_frames(arguments.sequence, clean, arguments.frames)
        shutil.copytree(clean, damaged)
        blank_frames(damaged, arguments.no_depth, arguments.black)
        for name, folder in (("unmodified", clean), ("damaged", damaged)):
            print(f"reconstructing the {name} copy ...", flush=True)
            metrics, wall_seconds = run(folder, Path(temp) / f"{name}_out", arguments.extra)
            trajectory = read_tum_trajectory(Path(temp) / f"{name}_out" / "trajectory.txt")
            good = np.setdiff1d(np.arange(len(trajectory.timestamps_s)), damaged_frames)
            after = good[good > max(damaged_frames, default=-1)]
            rows.append({
                "run": name, "frames": metrics.frames, "frames_lost": metrics.frames_lost,
                "frames_relocalised": metrics.frames_relocalised, "frames_tracked_by_depth": metrics.frames_tracked_by_depth,
                "frames_without_depth": metrics.frames_without_depth, "keyframes": metrics.keyframes,
                "warnings": metrics.warnings, "ate_all_cm": metrics.trajectory.ate_rmse_m * 100.0,
                "ate_good_frames_cm": ate_cm(trajectory, ground_truth, good),
                "ate_after_damage_cm": ate_cm(trajectory, ground_truth, after), "good_frames": int(len(good)),
                "black_frames_rmse_cm": black_frames_rmse_cm(trajectory, ground_truth, arguments.black),
                "wall_seconds": wall_seconds,
            })
    lines = ["| run | frames lost | relocalised | tracked by depth | without depth | keyframes | ATE all cm | "
             "ATE good frames cm | ATE after damage cm | error on the black frames cm |", "|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        black_cm = "-" if row["black_frames_rmse_cm"] is None else f"{row['black_frames_rmse_cm']:.2f}"
        lines.append(f"| {row['run']} | {row['frames_lost']} | {row['frames_relocalised']} | {row['frames_tracked_by_depth']} | "
                     f"{row['frames_without_depth']} | {row['keyframes']} | {row['ate_all_cm']:.2f} | "
                     f"{row['ate_good_frames_cm']:.2f} | {row['ate_after_damage_cm']:.2f} | {black_cm} |")
    print("\n".join(lines))
    result = {"date": datetime.datetime.now().isoformat(timespec="seconds"),
              "machine": describe_machine(),
              "command": " ".join(["python", "benchmarks/tracking_failure.py", *sys.argv[1:]]),
              "sequence": str(arguments.sequence), "no_depth_frames": arguments.no_depth, "black_frames": arguments.black,
              "rows": rows}
    atomic_write_text(arguments.output, json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
