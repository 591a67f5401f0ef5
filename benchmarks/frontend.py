"""Frontends side by side on real data: ORB without and with loop closure + global BA, the Open3D keyframe
frontend, and plain frame-to-frame Open3D RGB-D odometry (the peer).

    python benchmarks/frontend.py                                 # every sequence, full length
    python benchmarks/frontend.py --max-frames 200 --methods orb  # a subset
    python benchmarks/frontend.py --data /work/data --sequences rgbd_dataset_freiburg1_xyz   # one sequence

Sequences are named by folder and looked for in the ``--data`` folders (default: ``shared/data`` and ``data``
beside the repository); one that is missing stops the run at once with a line saying how to get it. A run on a
subset replaces its (method, sequence) rows in benchmarks/results/frontend.json and keeps the others.

Each (method, sequence) runs in its own process. frames/s counts only the time inside ``track`` and
``finish`` (reading and decoding images is excluded and reported apart as ``read s``); ``CPU frames/s`` divides
by the process CPU time over the same calls (all threads), which other processes on the machine disturb far
less than wall time, and ``load`` is the 1-minute load average when the row started; peak memory is the
child's ``ru_maxrss`` (read with wait4, so it includes the decoded images and Python itself). ATE is the RMSE
after SE(3) alignment; RPE is the translational RMSE between consecutive frames. The table goes to stdout,
the rows to benchmarks/results/frontend.json. 7-Scenes is read with colour resampled into the depth camera
(benchmarks/sequences.py); ``--unregistered-colour`` reads it pixel for pixel as its camera.txt says.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import describe_machine  # noqa: E402
from benchmarks.sequences import FR1_XYZ, FR1_XYZ_FIRST37, KITCHEN, add_data_argument, camera_file_for, find_sequence, merge_rows  # noqa: E402
from tambridge.files import atomic_write_text  # noqa: E402

SEQUENCES = (FR1_XYZ, KITCHEN, FR1_XYZ_FIRST37)
METHODS = {
    "orb": "ORB, no loop closure",
    "orb_loop": "ORB + loop closure + global BA",
    "open3d": "Open3D keyframes + pose graph",
    "open3d_f2f": "Open3D frame-to-frame (peer)",
}


def make_frontend(method: str, camera):
    from tambridge.frontend.open3d.frontend import Open3dFrontend
    from tambridge.frontend.open3d.odometry import FrameToFrameOdometry
    from tambridge.frontend.orb.frontend import OrbFrontend
    from tambridge.frontend.orb.config import OrbFrontendConfig

    if method == "orb":
        return OrbFrontend(camera, OrbFrontendConfig(loop_closure=False, global_ba=False))
    if method == "orb_loop":
        return OrbFrontend(camera, OrbFrontendConfig())
    if method == "open3d":
        return Open3dFrontend(camera)
    if method == "open3d_f2f":
        return FrameToFrameOdometry(camera)
    raise ValueError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")


def run_one(method: str, folder: Path, max_frames: int | None, output: Path, camera_file: Path | None) -> None:
    """Child process: track the sequence, evaluate, write one JSON row."""
    from tambridge.evaluation.trajectory import evaluate_trajectory
    from tambridge.io.tum import open_sequence

    sequence = open_sequence(folder, camera_file=camera_file, max_frames=max_frames)
    frontend = make_frontend(method, sequence.camera)
    tracking_s = reading_s = cpu_s = 0.0
    load = os.getloadavg()[0]
    for index in range(len(sequence)):
        started = time.perf_counter()
        frame = sequence[index]
        reading_s += time.perf_counter() - started
        started, cpu_started = time.perf_counter(), time.process_time()
        frontend.track(frame)
        tracking_s += time.perf_counter() - started
        cpu_s += time.process_time() - cpu_started
    started, cpu_started = time.perf_counter(), time.process_time()
    result = frontend.finish()
    tracking_s += time.perf_counter() - started
    cpu_s += time.process_time() - cpu_started
    errors = evaluate_trajectory(result.trajectory, sequence.ground_truth, align="se3")
    row = {
        "method": METHODS[method], "key": method, "sequence": folder.name, "frames": len(sequence),
        "camera_file": None if camera_file is None else str(camera_file.relative_to(ROOT)),
        "ate_cm": 100 * errors.ate_rmse_m, "rpe_cm": 100 * errors.rpe_trans_rmse_m, "rpe_deg": errors.rpe_rot_rmse_deg,
        "fps": len(sequence) / tracking_s, "tracking_s": tracking_s, "read_s": reading_s,
        "cpu_fps": len(sequence) / cpu_s, "cpu_s": cpu_s, "load_1min": load,
        "keyframes": len(result.keyframe_poses), "culled": result.keyframes_culled, "loops": result.loops_closed,
        "lost": result.frames_lost,
        "relocalised": result.frames_relocalised, "stage_s": result.timings_s,
    }
    atomic_write_text(output, json.dumps(row))


def run_child(method: str, folder: Path, max_frames: int | None, camera_file: Path | None) -> dict:
    with tempfile.TemporaryDirectory() as temp:
        output = Path(temp) / "row.json"
        command = [sys.executable, __file__, "--one", method, str(folder), str(output)]
        if camera_file is not None:
            command += ["--camera", str(camera_file)]
        if max_frames is not None:
            command += ["--max-frames", str(max_frames)]
        child = subprocess.Popen(command, cwd=ROOT)
        _, status, usage = os.wait4(child.pid, 0)
        code = os.waitstatus_to_exitcode(status)
        row = json.loads(output.read_text()) if code == 0 and output.is_file() else {
            "method": METHODS[method], "key": method, "sequence": folder.name}
        row.update(exit_status=code, peak_memory_mb=usage.ru_maxrss / 1024.0)
        return row


def format_table(rows: list[dict]) -> str:
    columns = [("sequence", "sequence", "{}"), ("method", "method", "{}"), ("frames", "frames", "{}"),
               ("ATE cm", "ate_cm", "{:.2f}"), ("RPE cm/frame", "rpe_cm", "{:.2f}"), ("RPE deg/frame", "rpe_deg", "{:.3f}"),
               ("frames/s", "fps", "{:.1f}"), ("CPU frames/s", "cpu_fps", "{:.1f}"), ("load", "load_1min", "{:.1f}"),
               ("read s", "read_s", "{:.1f}"), ("peak MB", "peak_memory_mb", "{:.0f}"),
               ("keyframes", "keyframes", "{}"), ("culled", "culled", "{}"), ("loops", "loops", "{}"), ("lost", "lost", "{}")]
    lines = ["| " + " | ".join(title for title, _, _ in columns) + " |", "|" + "---|" * len(columns)]
    for row in rows:
        cells = [("-" if row.get(key) is None else form.format(row[key])) for _, key, form in columns]
        lines.append("| " + " | ".join(cells) + " |")
    stage_lines = ["", "seconds per stage (ORB: features, matching incl. fusion, pnp incl. motion-only refinement, "
                   "local BA, loop incl. bag of words; Open3D: features = RGBD images and clouds, matching = odometry):"]
    for row in rows:
        if row.get("stage_s"):
            stages = ", ".join(f"{k} {v:.1f}" for k, v in row["stage_s"].items() if v > 0)
            stage_lines.append(f"  {row['sequence']} / {row['method']}: {stages}")
    return "\n".join(lines + stage_lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_data_argument(parser)
    parser.add_argument("--sequences", nargs="*", default=list(SEQUENCES), help="folder names (or paths)")
    parser.add_argument("--methods", nargs="*", default=list(METHODS), choices=list(METHODS))
    parser.add_argument("--max-frames", type=int)
    parser.add_argument("--unregistered-colour", action="store_true",
                        help="read 7-Scenes as its camera.txt says (colour taken pixel for pixel with depth)")
    parser.add_argument("--one", nargs=3, metavar=("METHOD", "FOLDER", "OUTPUT"), help=argparse.SUPPRESS)
    parser.add_argument("--camera", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        method, folder, output = args.one
        run_one(method, Path(folder), args.max_frames, Path(output), args.camera)
        return
    folders = [find_sequence(name, args.data) for name in args.sequences]  # all found before any run
    rows = []
    machine = describe_machine()
    command = " ".join(["python", "benchmarks/frontend.py", *sys.argv[1:]])
    for folder in folders:
        camera_file = camera_file_for(folder, registered_colour=not args.unregistered_colour)
        for method in args.methods:
            row = run_child(method, folder, args.max_frames, camera_file)
            row.update(date=datetime.datetime.now().isoformat(timespec="seconds"), command=command, machine=machine)
            rows.append(row)
            print(f"{folder.name} / {METHODS[method]}: done", file=sys.stderr, flush=True)
    table = format_table(rows)
    print(table)
    results = ROOT / "benchmarks" / "results" / "frontend.json"
    old = json.loads(results.read_text())["rows"] if results.is_file() else []
    report = {"command": command, "machine": machine,
              "rows": merge_rows(old, rows, ("key", "sequence", "frames", "camera_file"))}
    atomic_write_text(results, json.dumps(report, indent=2) + "\n")


if __name__ == "__main__":
    main()
