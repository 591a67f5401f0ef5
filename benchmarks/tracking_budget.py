"""Where tracking's frames/s go on this machine: the CPU each stage costs per frame, the frames/s those costs allow
on this machine's cores, and what the threaded pipeline reaches.

    python benchmarks/tracking_budget.py                                   # TUM fr1/xyz, two threaded runs
    python benchmarks/tracking_budget.py --sequence DIR --runs 3

1. **Budget** (one process, everything in one thread: the frontend with ``mapping_thread=false``, frames read one
   after the other): CPU milliseconds per frame (``time.thread_time``, so other processes do not count) for
   reading (decoding the images and, as the pipeline's reader does, scoring sharpness), ORB extraction (the
   frontend's ``extract``: what the pipeline's preparer thread runs), tracking (the rest of ``track``) and the
   mapping thread's work (local BA, loop closing and global BA from the frontend's stage timings, which run in that
   thread when it is on). Their sum bounds the frames/s on ``n`` cores at ``n * 1000 / sum``: the most that
   perfect overlap of the pipeline's four threads could give.
2. **Measured**: ``tambridge reconstruct SEQ --set mapper.enabled=false --set mesh.enabled=false`` (the default
   threaded pipeline, tracking only), ``--runs`` times, each in its own process: frames/s end to end
   (metrics.json), ATE, and the cores it kept busy (the child's CPU seconds over its wall seconds).

The table goes to stdout, the figures to benchmarks/results/tracking_budget.json.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.dense_tracking import orb_config  # noqa: E402
from benchmarks.machine import describe_machine  # noqa: E402
from benchmarks.sequences import FR1_XYZ, add_sequence_arguments, camera_file_for, find_sequence  # noqa: E402
from tambridge.files import atomic_write_text  # noqa: E402

MAPPING_THREAD_STAGES = ("local_ba", "loop", "global_ba")
"""The frontend's stages that run in its mapping thread when that is on (the rest run in the caller's)."""


def budget(folder: Path, camera_file: Path | None, max_frames: int | None) -> dict:
    """CPU ms per frame of each stage, everything in this thread (see the module docstring)."""
    from tambridge.evaluation.trajectory import evaluate_trajectory
    from tambridge.frontend.orb.frontend import OrbFrontend
    from tambridge.images import sharpness
    from tambridge.io.tum import open_sequence

    sequence = open_sequence(folder, camera_file=camera_file)
    frames = len(sequence) if max_frames is None else min(max_frames, len(sequence))
    frontend = OrbFrontend(sequence.camera, orb_config(["mapping_thread=false"]))
    reading_s = extraction_s = tracking_s = 0.0
    for index in range(frames):
        started = time.thread_time()
        frame = sequence[index]
        sharpness(frame.rgb)
        read = time.thread_time()
        features = frontend.extract(frame)
        extracted = time.thread_time()
        frontend.track(frame, features)
        reading_s += read - started
        extraction_s += extracted - read
        tracking_s += time.thread_time() - extracted
    started = time.thread_time()
    result = frontend.finish()
    tracking_s += time.thread_time() - started
    # Inline, the mapping thread's stages ran inside track and finish: move them out of tracking.
    mapping_s = sum(result.timings_s[stage] for stage in MAPPING_THREAD_STAGES)
    per_frame_ms = {"reading": reading_s, "extraction": extraction_s, "tracking": tracking_s - mapping_s,
                    "mapping_thread": mapping_s}
    per_frame_ms = {stage: 1e3 * seconds / frames for stage, seconds in per_frame_ms.items()}
    total_ms = sum(per_frame_ms.values())
    cores = os.cpu_count() or 1
    errors = evaluate_trajectory(result.trajectory, sequence.ground_truth, align="se3") if sequence.ground_truth is not None else None
    return {"frames": frames, "cpu_ms_per_frame": per_frame_ms, "cpu_ms_per_frame_total": total_ms, "cores": cores,
            "fps_bound": cores * 1e3 / total_ms, "fps_one_core": 1e3 / total_ms,
            "ate_cm_inline": None if errors is None else 100 * errors.ate_rmse_m}


def threaded_run(folder: Path, camera_file: Path | None, max_frames: int | None) -> dict:
    """One tracking-only run of the CLI in a child process: frames/s, ATE, cores kept busy."""
    with tempfile.TemporaryDirectory() as output:
        command = [sys.executable, str(ROOT / "cli.py"), "reconstruct", str(folder), "-o", output, "--quiet",
                   "--set", "mapper.enabled=false", "--set", "mesh.enabled=false"]
        if camera_file is not None:
            command += ["--camera", str(camera_file)]
        if max_frames is not None:
            command += ["--max-frames", str(max_frames)]
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        started = time.perf_counter()
        child = subprocess.run(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        wall_s = time.perf_counter() - started
        if child.returncode != 0:
            last = (child.stderr.strip().splitlines() or ["no message"])[-1]
            raise SystemExit(f"error: {folder}: the tracking-only run failed (exit {child.returncode}): {last}")
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        metrics = json.loads((Path(output) / "metrics.json").read_text())
    cpu_s = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    trajectory = metrics.get("trajectory") or {}
    return {"fps_end_to_end": metrics["fps_end_to_end"], "fps_tracking_stage": metrics["fps_per_stage"]["tracking"],
            "ate_cm": None if "ate_rmse_m" not in trajectory else 100 * trajectory["ate_rmse_m"],
            "process_wall_s": wall_s, "process_cpu_s": cpu_s, "cores_busy": cpu_s / wall_s}


def format_table(row: dict) -> str:
    stages = row["cpu_ms_per_frame"]
    runs = row["threaded_runs"]
    lines = [
        "| " + " | ".join([*(f"{stage} ms" for stage in stages), "total ms", f"bound on {row['cores']} cores fps",
                          "measured fps (runs)", "cores busy", "ATE cm (runs)"]) + " |",
        "|" + "---|" * (len(stages) + 5),
        "| " + " | ".join([*(f"{value:.1f}" for value in stages.values()), f"{row['cpu_ms_per_frame_total']:.1f}",
                          f"{row['fps_bound']:.1f}", ", ".join(f"{run['fps_end_to_end']:.1f}" for run in runs),
                          ", ".join(f"{run['cores_busy']:.2f}" for run in runs),
                          ", ".join("-" if run["ate_cm"] is None else f"{run['ate_cm']:.3f}" for run in runs)]) + " |",
    ]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_sequence_arguments(parser, FR1_XYZ)
    parser.add_argument("--max-frames", type=int)
    parser.add_argument("--runs", type=int, default=2, help="threaded runs of the CLI after the budget")
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks" / "results" / "tracking_budget.json")
    args = parser.parse_args()
    if args.runs < 0 or (args.max_frames is not None and args.max_frames < 2):
        parser.error("--runs must be at least 0 and --max-frames at least 2")
    folder = find_sequence(args.sequence, args.data)
    camera_file = camera_file_for(folder)
    row = budget(folder, camera_file, args.max_frames)
    row["threaded_runs"] = [threaded_run(folder, camera_file, args.max_frames) for _ in range(args.runs)]
    row.update(sequence=folder.name, date=datetime.datetime.now().isoformat(timespec="seconds"),
               command=" ".join(["python", "benchmarks/tracking_budget.py", *sys.argv[1:]]), machine=describe_machine())
    print(format_table(row))
    atomic_write_text(args.output, json.dumps(row, indent=2) + "\n")


if __name__ == "__main__":
    main()
