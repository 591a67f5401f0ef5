"""``tambridge batch`` on this machine: four synthetic sequences as one batch against four sequential runs.

    python benchmarks/batch.py                     # 4 x 20 frames at 160x120, default preset, mesh off
    python benchmarks/batch.py --frames 40 --set mapper.enabled=false

Measures, each in a fresh process as a user would run it: the wall and CPU seconds of each ``reconstruct`` run one
after the other (after one untimed run that fills numba's cache), with the default thread pools and again bounded
to ``--cpus-per-run`` threads as the batch bounds them, the wall seconds of the same four as one
``tambridge batch`` on a local Ray (``--cpus-per-run``), Ray's start-up overhead (``ray.init()``, a first empty
task, ``ray.shutdown()``) and the start-up of one run's process (interpreter and imports). Prints a table and
writes benchmarks/results/batch.json.
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

from benchmarks.machine import describe_machine  # noqa: E402
from pipelines.batch import THREAD_VARIABLES  # noqa: E402
from tambridge.evaluation.metrics import read_metrics  # noqa: E402
from tambridge.files import atomic_write_text  # noqa: E402
from tambridge.io.synthetic import SynthOptions, write_synthetic_sequence  # noqa: E402

SEQUENCES = 4
RAY_STARTUP = """
import json, time
started = time.perf_counter()
import ray
imported = time.perf_counter()
ray.init(include_dashboard=False, log_to_driver=False, object_store_memory=100 * 1024 * 1024)
initialised = time.perf_counter()
ray.get(ray.remote(lambda: None).remote())
first_task = time.perf_counter()
ray.shutdown()
print(json.dumps({"import_s": imported - started, "init_s": initialised - imported,
                  "first_task_s": first_task - initialised, "shutdown_s": time.perf_counter() - first_task}))
"""


def timed(command: list[str], threads: int | None = None) -> dict:
    """Run ``command`` (with its thread pools bounded to ``threads``, unless None); its wall seconds and the CPU
    seconds (user + system) of it and its children."""
    environment = dict(os.environ, PYTHONPATH=str(ROOT), RAY_USAGE_STATS_ENABLED="0")
    if threads is not None:
        environment.update({name: str(threads) for name in THREAD_VARIABLES})
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    done = subprocess.run(command, cwd=ROOT, env=environment, capture_output=True, text=True)
    wall_s = time.perf_counter() - started
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode not in (0,):
        sys.exit(f"{' '.join(command)} failed ({done.returncode}):\n{done.stderr[-2000:]}")
    cpu_s = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"wall_s": wall_s, "cpu_s": cpu_s, "stdout": done.stdout}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--size", default="160x120")
    parser.add_argument("--cpus-per-run", type=int, default=1)
    parser.add_argument("--set", dest="overrides", action="append", default=["mesh.enabled=false"])
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks" / "results" / "batch.json")
    arguments = parser.parse_args()
    width, height = (int(value) for value in arguments.size.split("x"))
    options = [argument for override in arguments.overrides for argument in ("--set", override)]
    cli = [sys.executable, str(ROOT / "cli.py")]

    with tempfile.TemporaryDirectory(prefix="tambridge-batch-bench-") as temp:
        temp = Path(temp)
        folders = []
        for index in range(SEQUENCES):
            folder = temp / "sequences" / f"synthetic{index}"
            write_synthetic_sequence(folder, SynthOptions(frame_count=arguments.frames, width=width, height=height,
                                                          seed=index))
            folders.append(folder)
        # Untimed: compiles numba's kernels into its on-disk cache, which every later process (and worker) reads.
        timed([*cli, "reconstruct", str(folders[0]), "-o", str(temp / "warm"), "--quiet", *options])
        process_startup = timed([sys.executable, "-c", "import cli, pipelines.reconstruct"])
        ray_startup = json.loads(timed([sys.executable, "-c", RAY_STARTUP])["stdout"].strip().splitlines()[-1])

        sequential = {}
        for mode, threads in (("default_threads", None), ("bounded_threads", arguments.cpus_per_run)):
            sequential[mode] = []
            for folder in folders:
                run_dir = temp / mode / folder.name
                run = timed([*cli, "reconstruct", str(folder), "-o", str(run_dir), "--quiet", *options], threads)
                metrics = read_metrics(run_dir / "metrics.json")
                sequential[mode].append({"sequence": folder.name, "wall_s": run["wall_s"], "cpu_s": run["cpu_s"],
                                         "run_seconds_total": metrics.seconds_total,
                                         "peak_memory_mb": metrics.peak_memory_mb})
        batch = timed([*cli, "batch", *map(str, folders), "-o", str(temp / "batch"), "--quiet",
                       "--cpus-per-run", str(arguments.cpus_per_run), *options])
        summary = json.loads((temp / "batch" / "summary.json").read_text())
        statuses = sorted({row["status"] for row in summary["sequences"]})
        if statuses != ["finished"]:
            sys.exit(f"the batch did not finish every sequence: {statuses}")

    totals = {mode: {"wall_s": sum(run["wall_s"] for run in runs), "cpu_s": sum(run["cpu_s"] for run in runs)}
              for mode, runs in sequential.items()}
    bounded = totals["bounded_threads"]
    frames = SEQUENCES * arguments.frames
    result = {
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "machine": describe_machine(),
        "load_average_1min_at_end": os.getloadavg()[0],
        "command": "python benchmarks/batch.py " + " ".join(sys.argv[1:]),
        "sequences": SEQUENCES, "frames_per_sequence": arguments.frames, "size": arguments.size,
        "overrides": arguments.overrides, "cpus_per_run": arguments.cpus_per_run,
        "sequential": sequential,
        "sequential_totals": totals,
        "batch_wall_s": batch["wall_s"],
        "speedup_over_default_threads": totals["default_threads"]["wall_s"] / batch["wall_s"],
        "speedup_over_bounded_threads": bounded["wall_s"] / batch["wall_s"],
        "cpu_s_per_sequence": bounded["cpu_s"] / SEQUENCES,
        "cpu_s_per_frame": bounded["cpu_s"] / frames,
        "process_startup_wall_s": process_startup["wall_s"],
        "ray_startup": ray_startup,
        "batch_nodes": sorted({row["node"] for row in summary["sequences"]}),
    }
    atomic_write_text(arguments.output, json.dumps(result, indent=2) + "\n")

    print(f"{SEQUENCES} sequences x {arguments.frames} frames at {arguments.size}, {result['machine']}")
    print(f"{'sequence':<12} {'threads':<16} {'wall s':>8} {'CPU s':>8} {'run s':>8} {'peak MiB':>9}")
    for mode, runs in sequential.items():
        for run in runs:
            print(f"{run['sequence']:<12} {mode:<16} {run['wall_s']:8.1f} {run['cpu_s']:8.1f} "
                  f"{run['run_seconds_total']:8.1f} {run['peak_memory_mb']:9.0f}")
        print(f"{'sequential':<12} {mode:<16} {totals[mode]['wall_s']:8.1f} {totals[mode]['cpu_s']:8.1f}")
    print(f"{'batch':<12} {'bounded_threads':<16} {batch['wall_s']:8.1f}   speed-up "
          f"{result['speedup_over_bounded_threads']:.2f}x over bounded, {result['speedup_over_default_threads']:.2f}x "
          f"over default threads (--cpus-per-run {arguments.cpus_per_run})")
    print(f"Ray start-up: import {ray_startup['import_s']:.1f} s, init {ray_startup['init_s']:.1f} s, first task "
          f"{ray_startup['first_task_s']:.1f} s, shutdown {ray_startup['shutdown_s']:.1f} s; one run's process "
          f"start-up {process_startup['wall_s']:.1f} s; load average {result['load_average_1min_at_end']:.1f}")
    print(f"wrote {arguments.output}")


if __name__ == "__main__":
    main()
