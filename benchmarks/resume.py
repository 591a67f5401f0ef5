"""Kill a ``reconstruct`` run with SIGKILL at several moments, resume each with ``--resume``, and compare with an
uninterrupted run: what a user who never planned for a crash gets back.

    python benchmarks/resume.py --sequence DATA/7scenes_redkitchen_0-699 --camera configs/cameras/7scenes_kinect.yaml

Every run uses the default preset and the default checkpoint settings, with ``mesh.enabled=false`` and the ORB
frontend's keyframe work inline (``frontend.orb.mapping_thread=false``) so that runs are deterministic and a resumed
run can be compared pose by pose. The uninterrupted run comes first; the kills fall at ``--moments`` (fractions of
its wall time). Prints, per kill, where the checkpoint was, the largest position difference of the resumed
trajectory to the uninterrupted one and the checkpoint's size; and the uninterrupted run's checkpoint overhead
(its ``checkpoint`` stage over its end-to-end seconds). Writes benchmarks/results/resume.json.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import describe_machine  # noqa: E402
from tambridge.checkpoint import checkpoint_path, find_checkpoint  # noqa: E402
from tambridge.errors import CheckpointError  # noqa: E402
from tambridge.evaluation.metrics import read_metrics  # noqa: E402
from tambridge.files import atomic_write_text  # noqa: E402


def checkpoint_frame(path: Path) -> int | None:
    """The next frame of the checkpoint at ``path``; None where there is none (or it is being replaced)."""
    try:
        checkpoint = find_checkpoint(path)
    except CheckpointError:
        return None
    return None if checkpoint is None else checkpoint.next_frame


def kill(command: list[str], out: Path, options: list[str], delay_s: float) -> float:
    """Start a run into ``out`` and SIGKILL it after ``delay_s``; a run that finishes sooner (the machine got
    faster) is removed and started again with a shorter delay. Returns the delay it was killed after."""
    for _ in range(4):
        child = subprocess.Popen([*command, "-o", str(out), *options, "--overwrite"], stdout=subprocess.DEVNULL,
                                 stderr=subprocess.DEVNULL)
        try:
            child.wait(timeout=delay_s)
        except subprocess.TimeoutExpired:
            child.send_signal(signal.SIGKILL)
            child.wait()
            return delay_s
        delay_s *= 0.75
    sys.exit(f"{out}: every run ended before it could be killed")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sequence", type=Path, required=True)
    parser.add_argument("--camera", type=Path, help="camera file of the sequence (7-Scenes: configs/cameras/7scenes_kinect.yaml)")
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--moments", type=float, nargs="+", default=[0.1, 0.3, 0.5, 0.7, 0.9],
                        help="when to kill, as fractions of the uninterrupted run's wall time")
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks" / "results" / "resume.json")
    arguments = parser.parse_args()
    options = ["--quiet", "--max-frames", str(arguments.frames), "--set", "mesh.enabled=false",
               "--set", "frontend.orb.mapping_thread=false",
               *(["--camera", str(arguments.camera)] if arguments.camera else [])]
    command = [sys.executable, str(ROOT / "cli.py"), "reconstruct", str(arguments.sequence)]
    result = {"date": datetime.datetime.now().isoformat(timespec="seconds"),
              "machine": describe_machine(),
              "load_average": os.getloadavg()[0],
              "command": " ".join(["python", "benchmarks/resume.py", *sys.argv[1:]]), "options": options, "kills": []}
    with tempfile.TemporaryDirectory(prefix="tambridge-resume-") as temp:
        full = Path(temp) / "full"
        started = time.perf_counter()
        subprocess.run([*command, "-o", str(full), *options], check=True, stdout=subprocess.DEVNULL)
        full_wall_s = time.perf_counter() - started
        metrics = read_metrics(full / "metrics.json")
        checkpoint_s = metrics.seconds_per_stage.get("checkpoint", 0.0)
        result["uninterrupted"] = {"wall_seconds": full_wall_s, "seconds_total": metrics.seconds_total,
                                   "checkpoint_seconds": checkpoint_s,
                                   "checkpoint_share": checkpoint_s / metrics.seconds_total,
                                   "keyframes": metrics.keyframes, "gaussians": metrics.map.gaussians}
        print(f"uninterrupted: {full_wall_s:.0f} s, {metrics.keyframes} keyframes; checkpoints {checkpoint_s:.2f} s = "
              f"{100 * checkpoint_s / metrics.seconds_total:.2f} % of {metrics.seconds_total:.0f} s end to end", flush=True)
        reference = np.loadtxt(full / "trajectory.txt")
        print(f"{'kill at':>8} {'checkpoint frame':>17} {'checkpoint MB':>14} {'max position diff (mm)':>23} "
              f"{'same timestamps':>16}")
        for moment in arguments.moments:
            out = Path(temp) / f"killed_{moment:.2f}"
            delay_s = kill(command, out, options, moment * full_wall_s)
            frame = checkpoint_frame(checkpoint_path(out))
            size_mb = checkpoint_path(out).stat().st_size / 1e6 if frame is not None else 0.0
            subprocess.run([*command, "-o", str(out), *options, "--resume"], check=True, stdout=subprocess.DEVNULL)
            resumed = np.loadtxt(out / "trajectory.txt")
            same_stamps = resumed.shape == reference.shape and bool(np.array_equal(resumed[:, 0], reference[:, 0]))
            difference_m = float(np.abs(resumed[:, 1:4] - reference[:, 1:4]).max()) if same_stamps else float("nan")
            row = {"moment": moment, "killed_after_s": delay_s, "checkpoint_frame": frame,
                   "checkpoint_mb": size_mb, "max_position_difference_m": difference_m,
                   "every_frame_posed": same_stamps}
            result["kills"].append(row)
            print(f"{moment:>8.2f} {str(frame):>17} {size_mb:>14.1f} {difference_m * 1000:>23.6f} {str(same_stamps):>16}",
                  flush=True)
    atomic_write_text(arguments.output, json.dumps(result, indent=2) + "\n")
    print(f"wrote {arguments.output}")


if __name__ == "__main__":
    main()
