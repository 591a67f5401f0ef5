"""The fast turns of 7-Scenes redkitchen (frames 100-150 and 450-550) tracked by the ORB frontend, the Open3D
keyframe frontend and COLMAP, against KinectFusion's poses with SE(3) and with Sim(3) alignment: what any of them
reaches there, and how much of the error a scale between the depth's metres and the reference's takes.

    python benchmarks/turns.py                                       # both turns, all three methods
    python benchmarks/turns.py --segments 450-550 --methods orb open3d
    python benchmarks/turns.py --sequence DIR --segments 0-100       # another sequence: a folder or a name

Each segment becomes a TUM-layout folder of links to the sequence's files (its colour frames, their depth, the
ground truth within their time span, the folder's camera.yaml), under ``--work``, and each method runs as a user
runs it: ``tambridge reconstruct`` tracking only (``mapper.enabled=false``, ``mesh.enabled=false``), with the
default preset (``orb``) or ``configs/open3d.yaml`` (``open3d``), and ``tambridge colmap --every 1`` (``colmap``:
colour only, so its trajectory has its own scale and only Sim(3) applies). A segment is tracked from scratch, as
a sequence of its own. ATE is the RMSE of the aligned positions over the frames with ground truth; ``scale`` is the
Sim(3) alignment's (estimate to reference); RPE the translational RMSE between consecutive frames (SE(3)-aligned,
Sim(3) for COLMAP). The table goes to stdout, the rows to ``--output`` (benchmarks/results/turns.json).
"""

from __future__ import annotations

import argparse
import datetime
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import describe_machine  # noqa: E402
from benchmarks.sequences import KITCHEN, add_sequence_arguments, camera_file_for, find_sequence  # noqa: E402
from tambridge.files import atomic_write_text  # noqa: E402

METHODS = ("orb", "open3d", "colmap")
SEGMENTS = ("100-150", "450-550")
GROUND_TRUTH_MARGIN_S = 0.02
"""Ground-truth lines kept this far beyond a segment's first and last colour stamps (the evaluation associates
within 20 ms)."""


def write_segment(sequence: Path, start: int, end: int, folder: Path) -> Path:
    """A TUM-layout folder of links to colour frames ``start..end-1`` of ``sequence`` (indices into rgb.txt, read by
    :func:`~tambridge.io.tum.read_file_list`), the same rows of depth.txt when it lists one depth image per colour
    frame (else all of them: the reader associates them), the ground truth within the frames' span and the folder's
    camera.yaml; returns ``folder``."""
    from tambridge.io.tum import read_file_list
    from tambridge.trajectory import Trajectory, read_tum_trajectory, write_tum_trajectory

    colour, depth = read_file_list(sequence / "rgb.txt"), read_file_list(sequence / "depth.txt")
    if not 0 <= start < end <= len(colour):
        raise SystemExit(f"{sequence}: segment {start}-{end} lies outside its {len(colour)} colour frames")
    kept = {"rgb.txt": colour[start:end], "depth.txt": depth[start:end] if len(depth) == len(colour) else depth}
    truth = read_tum_trajectory(sequence / "groundtruth.txt")
    within = ((truth.timestamps_s >= kept["rgb.txt"][0][0] - GROUND_TRUTH_MARGIN_S)
              & (truth.timestamps_s <= kept["rgb.txt"][-1][0] + GROUND_TRUTH_MARGIN_S))
    folder.mkdir(parents=True, exist_ok=True)
    write_tum_trajectory(folder / "groundtruth.txt", Trajectory(truth.timestamps_s[within], truth.world_from_camera[within]))
    for listing, entries in kept.items():
        (folder / listing).write_text("".join(f"{stamp:.6f} {name}\n" for stamp, name in entries))
        for _, name in entries:
            link = folder / name
            link.parent.mkdir(parents=True, exist_ok=True)
            if not link.is_symlink():
                link.symlink_to((sequence / name).resolve())
    if (sequence / "camera.yaml").is_file() and not (folder / "camera.yaml").exists():
        (folder / "camera.yaml").symlink_to((sequence / "camera.yaml").resolve())
    return folder


def run_method(method: str, segment: Path, camera_file: Path | None, out: Path) -> float:
    """Run ``method`` on the ``segment`` folder into ``out`` as the CLI does; returns its wall seconds."""
    camera = [] if camera_file is None else ["--camera", str(camera_file)]
    if method == "colmap":
        command = ["colmap", str(segment), "--every", "1", *camera]
    else:
        preset = ["--config", str(ROOT / "configs" / "open3d.yaml")] if method == "open3d" else []
        command = ["reconstruct", str(segment), *camera, *preset, "--set", "mapper.enabled=false", "--set",
                   "mesh.enabled=false", "--overwrite", "--quiet"]
    started = time.perf_counter()
    child = subprocess.run([sys.executable, str(ROOT / "cli.py"), *command, "-o", str(out)], cwd=ROOT,
                           capture_output=True, text=True)
    if child.returncode != 0:
        raise SystemExit(f"{method} on {segment}: exit {child.returncode}: {child.stderr.strip().splitlines()[-1:]}")
    return time.perf_counter() - started


def scores(estimate_path: Path, truth_path: Path, method: str) -> dict:
    """ATE (cm) with SE(3) and Sim(3) alignment, the Sim(3) scale, the largest errors and RPE."""
    from tambridge.evaluation.trajectory import evaluate_trajectory
    from tambridge.trajectory import read_tum_trajectory

    estimate, truth = read_tum_trajectory(estimate_path), read_tum_trajectory(truth_path)
    similarity = evaluate_trajectory(estimate, truth, align="sim3")
    row = {"poses": similarity.pose_count, "ate_sim3_cm": 100 * similarity.ate_rmse_m,
           "max_sim3_cm": 100 * similarity.ate_max_m, "scale": similarity.scale,
           "ate_se3_cm": None, "max_se3_cm": None, "rpe_cm": 100 * similarity.rpe_trans_rmse_m}
    if method != "colmap":
        rigid = evaluate_trajectory(estimate, truth, align="se3")
        row.update(ate_se3_cm=100 * rigid.ate_rmse_m, max_se3_cm=100 * rigid.ate_max_m,
                   rpe_cm=100 * rigid.rpe_trans_rmse_m)
    return row


def parse_segment(text: str) -> tuple[int, int]:
    start, _, end = text.partition("-")
    try:
        return int(start), int(end)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text}: give START-END, colour frame indices, e.g. 450-550") from None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_sequence_arguments(parser, KITCHEN)
    parser.add_argument("--segments", nargs="*", type=parse_segment, default=[parse_segment(s) for s in SEGMENTS],
                        metavar="START-END")
    parser.add_argument("--methods", nargs="*", default=list(METHODS), choices=METHODS)
    parser.add_argument("--work", type=Path, default=ROOT / "benchmarks" / "results" / "runs" / "turns",
                        help="segment folders and run outputs")
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks" / "results" / "turns.json")
    arguments = parser.parse_args()
    sequence = find_sequence(arguments.sequence, arguments.data)
    camera_file = camera_file_for(sequence)
    rows = []
    # Every segment is written (and checked) before any method runs.
    segments = [(f"{start}-{end}", write_segment(sequence, start, end, arguments.work / f"{sequence.name}_{start}-{end}"))
                for start, end in arguments.segments]
    print(f"{'segment':>9} {'method':>7} {'poses':>5} {'SE(3) ATE / max cm':>19} {'Sim(3) ATE / max cm':>20} "
          f"{'scale':>6} {'RPE cm':>7} {'s':>6}")
    for name, segment in segments:
        for method in arguments.methods:
            out = arguments.work / f"{segment.name}__{method}"
            seconds = run_method(method, segment, camera_file, out)
            row = {"sequence": sequence.name, "segment": name, "method": method, "seconds": seconds,
                   **scores(out / "trajectory.txt", segment / "groundtruth.txt", method)}
            rows.append(row)
            se3 = "-" if row["ate_se3_cm"] is None else f"{row['ate_se3_cm']:.2f} / {row['max_se3_cm']:.2f}"
            sim3 = f"{row['ate_sim3_cm']:.2f} / {row['max_sim3_cm']:.2f}"
            print(f"{row['segment']:>9} {method:>7} {row['poses']:>5} {se3:>19} {sim3:>20} {row['scale']:>6.3f} "
                  f"{row['rpe_cm']:>7.3f} {seconds:>6.1f}", flush=True)
    report = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "machine": describe_machine(),
              "command": " ".join(sys.argv), "rows": rows}
    atomic_write_text(arguments.output, json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
