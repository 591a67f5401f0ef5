"""Kill a ``reconstruct`` run with SIGKILL, resume it with ``--resume``, and compare with an uninterrupted run.

    python benchmarks/resume.py                                   # 7-Scenes, 120 frames, inline ORB mapping
    python benchmarks/resume.py --extra --set frontend.orb.mapping_thread=true

The killed run checkpoints every ``--every`` keyframes and is killed once a checkpoint at frame ``--kill-after``
or later exists. Both runs use the default preset with ``mesh.enabled=false``. Prints the largest position
difference between the two trajectories, ATE, novel-view PSNR and the checkpoint's size, and writes
benchmarks/results/resume.json.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tambridge.checkpoint import checkpoint_path, load_checkpoint
from tambridge.errors import CheckpointError  # noqa: E402
from tambridge.evaluation.metrics import read_metrics  # noqa: E402
from tambridge.files import atomic_write_text  # noqa: E402

DEFAULT_SEQUENCE = ROOT.parent / "shared" / "data" / "7scenes_redkitchen_0-699"


def checkpoint_frame(path: Path) -> int:
    """The next frame of the checkpoint at ``path``, -1 when there is none (yet)."""
    try:
        return load_checkpoint(path).next_frame
    except CheckpointError:
        return -1


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sequence", type=Path, default=DEFAULT_SEQUENCE)
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--every", type=int, default=4, help="checkpoint.every_keyframes")
    parser.add_argument("--kill-after", type=int, default=60, help="kill once a checkpoint at this frame exists")
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks" / "results" / "resume.json")
    parser.add_argument("--extra", nargs=argparse.REMAINDER, default=["--set", "frontend.orb.mapping_thread=false"],
                        help="further reconstruct options (last on the line)")
    arguments = parser.parse_args()
    options = ["--quiet", "--max-frames", str(arguments.frames), "--set", "mesh.enabled=false",
               "--set", f"checkpoint.every_keyframes={arguments.every}", *arguments.extra]
    command = [sys.executable, str(ROOT / "cli.py"), "reconstruct", str(arguments.sequence)]
    result = {"date": datetime.datetime.now().isoformat(timespec="seconds"),
              "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
              "command": " ".join(["python", "benchmarks/resume.py", *sys.argv[1:]]), "options": options}
    with tempfile.TemporaryDirectory(prefix="tambridge-resume-") as temp:
        killed, full = Path(temp) / "killed", Path(temp) / "full"
        started = time.perf_counter()
        child = subprocess.Popen([*command, "-o", str(killed), *options], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        while child.poll() is None and checkpoint_frame(checkpoint_path(killed)) < arguments.kill_after:
            time.sleep(0.5)
        child.send_signal(signal.SIGKILL)
        child.wait()
        if child.returncode != -signal.SIGKILL:
            sys.exit(f"the run ended (exit {child.returncode}) before it could be killed; lower --kill-after")
        checkpoint = checkpoint_path(killed)
        result.update(killed_after_s=time.perf_counter() - started, checkpoint_frame=checkpoint_frame(checkpoint),
                      checkpoint_mb=checkpoint.stat().st_size / 1e6,
                      outputs_after_kill=sorted(p.name for p in killed.iterdir()))
        print(f"killed after {result['killed_after_s']:.0f} s at the checkpoint of frame {result['checkpoint_frame']} "
              f"({result['checkpoint_mb']:.1f} MB); left: {', '.join(result['outputs_after_kill'])}", flush=True)
        for name, out, extra in (("resumed", killed, ["--resume"]), ("uninterrupted", full, [])):
            started = time.perf_counter()
            subprocess.run([*command, "-o", str(out), *options, *extra], check=True, stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL)
            metrics = read_metrics(out / "metrics.json")
            result[name] = {"wall_seconds": time.perf_counter() - started,
                            "ate_cm": metrics.trajectory.ate_rmse_m * 100.0,
                            "novel_psnr_db": metrics.map.rendering.novel_views.psnr_db,
                            "gaussians": metrics.map.gaussians, "keyframes": metrics.keyframes,
                            "checkpoint_seconds": metrics.seconds_per_stage.get("checkpoint", 0.0)}
            print(f"{name}: {result[name]}", flush=True)
        positions = [np.loadtxt(out / "trajectory.txt")[:, 1:4] for out in (killed, full)]
        result["max_position_difference_m"] = float(np.abs(positions[0] - positions[1]).max())
    print(f"largest position difference: {result['max_position_difference_m'] * 1000:.3f} mm; novel-view PSNR "
          f"{result['resumed']['novel_psnr_db']:.3f} dB resumed, {result['uninterrupted']['novel_psnr_db']:.3f} dB uninterrupted")
    atomic_write_text(arguments.output, json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
