"""Peak memory of ``tambridge reconstruct`` against the number of frames: does it grow with the map or the input?

    python benchmarks/memory.py                               # 100, 300, 700 frames of 7-Scenes, default preset
    python benchmarks/memory.py --frames 100 300 --extra --set mapper.enabled=false

Every length is one ``reconstruct`` run (default preset, mapping on, mesh on) in its own process, so each peak is
that process's own ``ru_maxrss`` (read with wait4), not the largest of several runs. The map's size comes from the
run's metrics.json (Gaussians, keyframes, mapping views), and so does the peak of the online part alone
(``peak_memory_mb_tracking``: tracking and mapping every frame, before exports and evaluation). If memory followed
the frames, the 700-frame run would need about 7x the 100-frame run's growth over the baseline (a process that only
imports what a run imports); if it follows the map, the growth tracks the Gaussian count. Resident memory is also
sampled every RSS_SAMPLE_S seconds into the JSON. Prints a table and writes benchmarks/results/memory.json.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import describe_machine  # noqa: E402
from tambridge.evaluation.metrics import read_metrics  # noqa: E402
from tambridge.files import atomic_write_text  # noqa: E402

DEFAULT_SEQUENCE = ROOT.parent / "shared" / "data" / "7scenes_redkitchen_0-699"
DEFAULT_FRAMES = (100, 300, 700)
BASELINE_CODE = "import cli, pipelines.reconstruct"
"""What the baseline process imports: everything a reconstruct run loads before its first frame."""
RSS_SAMPLE_S = 2.0
"""Interval of the resident-memory samples kept in the JSON (the peak itself comes from wait4, not from them)."""


def _rss_mb(pid: int) -> float | None:
    """Current resident memory of a process in MiB (Linux /proc), None once it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except (FileNotFoundError, ProcessLookupError, ValueError):
        return None
    return None


def peak_rss_mb(command: list[str], log_path: Path, samples: list | None = None) -> tuple[int, float, float]:
    """Run ``command`` in a child process (output to ``log_path``); returns (exit status, peak RSS MiB, seconds).

    ``samples``, when given, gets ``(seconds since start, RSS MiB)`` every RSS_SAMPLE_S while the child runs.
    """
    started = time.perf_counter()
    with open(log_path, "w") as log:
        child = subprocess.Popen(command, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
        # wait4 without blocking between samples: polling through Popen would reap the child and lose its usage.
        pid, status, usage = os.wait4(child.pid, 0 if samples is None else os.WNOHANG)
        while pid == 0:
            rss = _rss_mb(child.pid)
            if rss is not None:
                samples.append((round(time.perf_counter() - started, 1), round(rss, 1)))
            time.sleep(RSS_SAMPLE_S)
            pid, status, usage = os.wait4(child.pid, os.WNOHANG)
    # Linux reports ru_maxrss in KiB.
    return os.waitstatus_to_exitcode(status), usage.ru_maxrss / 1024.0, time.perf_counter() - started


def run_length(sequence: Path, frames: int, out: Path, extra: list[str]) -> dict:
    """One reconstruct run over the first ``frames`` frames; returns its row."""
    command = [sys.executable, str(ROOT / "cli.py"), "reconstruct", str(sequence), "-o", str(out), "--quiet",
               "--max-frames", str(frames), *extra]
    out.parent.mkdir(parents=True, exist_ok=True)
    samples: list[tuple[float, float]] = []
    status, peak_mb, seconds = peak_rss_mb(command, out.parent / f"{out.name}.log", samples)
    row = {"frames": frames, "exit_status": status, "peak_memory_mb": peak_mb, "wall_seconds": seconds, "extra": extra,
           "rss_samples_s_mb": samples}
    metrics_path = out / "metrics.json"
    if metrics_path.is_file():
        metrics = read_metrics(metrics_path)
        row.update(frames=metrics.frames, keyframes=metrics.keyframes,
                   gaussians=metrics.map.gaussians if metrics.map is not None else None,
                   peak_memory_mb_tracking=metrics.peak_memory_mb_tracking,
                   mapping_views=metrics.map.mapping_views if metrics.map is not None else None,
                   fps=metrics.fps_end_to_end, seconds_per_stage=metrics.seconds_per_stage)
    return row


def format_table(rows: list[dict], baseline_mb: float) -> str:
    """A Markdown table: frames, peak MB, growth over the import baseline, Gaussians, keyframes, fps."""
    lines = ["| frames | peak MB | over baseline MB | peak MB while tracking | Gaussians | keyframes | mapping views | "
             "frames/s | wall s |", "|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        if row["exit_status"] != 0:
            lines.append(f"| {row['frames']} | failed (exit {row['exit_status']}) | | | | | | | |")
            continue
        tracking_mb = row.get("peak_memory_mb_tracking")
        lines.append(f"| {row['frames']} | {row['peak_memory_mb']:.0f} | {row['peak_memory_mb'] - baseline_mb:.0f} | "
                     f"{'-' if tracking_mb is None else f'{tracking_mb:.0f}'} | "
                     f"{row.get('gaussians') or '-'} | {row.get('keyframes', '-')} | {row.get('mapping_views') or '-'} | "
                     f"{row.get('fps', float('nan')):.2f} | {row['wall_seconds']:.0f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sequence", type=Path, default=DEFAULT_SEQUENCE)
    parser.add_argument("--frames", type=int, nargs="+", default=list(DEFAULT_FRAMES))
    parser.add_argument("--extra", nargs=argparse.REMAINDER, default=[],
                        help="further reconstruct options for every run, e.g. --set mapper.enabled=false")
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks" / "results" / "memory.json")
    arguments = parser.parse_args()
    if not (arguments.sequence / "rgb.txt").is_file():
        parser.error(f"{arguments.sequence}: not a TUM-layout sequence (no rgb.txt); pass --sequence")
    runs = ROOT / "benchmarks" / "results" / "runs"
    runs.mkdir(parents=True, exist_ok=True)
    _, baseline_mb, _ = peak_rss_mb([sys.executable, "-c", BASELINE_CODE], runs / "memory_baseline.log")
    print(f"baseline (interpreter + imports): {baseline_mb:.0f} MB", flush=True)
    rows = []
    for frames in arguments.frames:
        print(f"reconstruct, first {frames} frames ...", flush=True)
        rows.append(run_length(arguments.sequence, frames, runs / f"memory_{arguments.sequence.name}_{frames}", arguments.extra))
        print(f"  peak {rows[-1]['peak_memory_mb']:.0f} MB in {rows[-1]['wall_seconds']:.0f} s", flush=True)
    table = format_table(rows, baseline_mb)
    print(table)
    machine = describe_machine()
    command = " ".join(["python", "benchmarks/memory.py", *sys.argv[1:]])
    result = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "machine": machine, "command": command,
              "sequence": str(arguments.sequence), "baseline_memory_mb": baseline_mb, "rows": rows}
    atomic_write_text(arguments.output, json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
