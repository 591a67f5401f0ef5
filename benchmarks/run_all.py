"""One benchmark over the real data: tambridge against its peers, side by side, on the same machine.

    python benchmarks/run_all.py                                  # every sequence with ground truth, full length
    python benchmarks/run_all.py --data ../shared/data --quick    # first 100 frames of each
    python benchmarks/run_all.py --gpu                            # tambridge's mapping on CUDA (gsplat); stops at once without CUDA
    python benchmarks/run_all.py --sequences rgbd_dataset_freiburg1_xyz --methods "tambridge default"

``--data`` names the folders that hold the sequences (default: ``shared/data`` and ``data`` beside the
repository); every sub-folder with rgb.txt, depth.txt and groundtruth.txt is a sequence, the first of a name wins.
``--sequences`` picks some by folder name (or path); one that is in no folder stops the run at once with a line
saying how to get it. A run on a subset replaces its (sequence, method) rows in run_all.json and keeps the others.

With ``--gpu`` every tambridge run gets ``--device cuda`` (its Gaussian map, bridge and rendering evaluation run on
the GPU through gsplat; tracking, mesh and COLMAP stay on the CPU), and each row says which device ran it.

Each method runs as its own process (its peak memory is that process's ru_maxrss, read with wait4), writes its
usual output folder under benchmarks/results/runs/, and the table is printed, written to
benchmarks/results/run_all.json and copied into docs/benchmarks.md between the results markers.
"""

from __future__ import annotations

import argparse
import dataclasses
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
from benchmarks.sequences import FR1_XYZ, add_data_argument, camera_file_for, find_sequence, merge_rows  # noqa: E402
from tambridge.evaluation.metrics import read_metrics  # noqa: E402
from tambridge.evaluation.trajectory import evaluate_trajectory  # noqa: E402
from tambridge.files import atomic_write_text  # noqa: E402
from tambridge.io.tum import open_sequence  # noqa: E402
from tambridge.trajectory import read_tum_trajectory  # noqa: E402

RESULTS_START = "<!-- results:start -->"
RESULTS_END = "<!-- results:end -->"


@dataclasses.dataclass(frozen=True)
class Method:
    """A way to run the data: a CLI invocation and whether its trajectory is monocular (Sim(3)-aligned)."""

    name: str
    command: tuple[str, ...]
    monocular: bool = False
    # False: read the folder with its own camera file even where CAMERA_FILES has a better one (the ablation).
    registered_colour: bool = True


METHODS = (
    Method("tambridge default", ("reconstruct", "--config", "configs/default.yaml")),
    Method("tambridge fast", ("reconstruct", "--config", "configs/fast.yaml")),
    Method("tambridge bridge off", ("reconstruct", "--set", "bridge.enabled=false")),
    Method("tambridge open3d frontend", ("reconstruct", "--config", "configs/open3d.yaml")),
    Method("open3d frame-to-frame", ("reconstruct", "--set", "frontend.kind=open3d_f2f", "--set", "mapper.enabled=false",
                                     "--set", "mesh.enabled=false")),
    Method("COLMAP (pycolmap, every 5th frame)", ("colmap", "--every", "5"), monocular=True),
    Method("tambridge default, colour not registered", ("reconstruct", "--config", "configs/default.yaml"),
           registered_colour=False),
)


def sequences_with_ground_truth(data: list[Path]) -> list[Path]:
    """Folders under the ``data`` folders that are TUM-layout sequences (rgb.txt, depth.txt) with groundtruth.txt
    and >= 10 frames; a name found in two folders counts once (the first)."""
    found = {}
    for parent in data:
        if not Path(parent).is_dir():
            continue
        for folder in sorted(p for p in Path(parent).iterdir() if p.is_dir()):
            if folder.name in found:
                continue
            if all((folder / name).is_file() for name in ("rgb.txt", "depth.txt", "groundtruth.txt")):
                if len(open_sequence(folder, check_depth_scale=False)) >= 10:
                    found[folder.name] = folder
    return list(found.values())


def run_method(method: Method, sequence: Path, out: Path, max_frames: int | None, device: str = "cpu") -> dict:
    """Run one method on one sequence in a child process; returns its row of the table.

    ``device`` goes to tambridge runs (``reconstruct --device``); other methods run on the CPU.
    """
    command = [sys.executable, str(ROOT / "cli.py"), *method.command, str(sequence), "-o", str(out)]
    camera_file = camera_file_for(sequence, method.registered_colour)
    if camera_file is not None:  # every method reads the sequence the same way
        command += ["--camera", str(camera_file)]
    if method.command[0] == "reconstruct":
        # A rerun replaces this benchmark's own earlier output folder (a finished run is refused otherwise).
        command += ["--quiet", "--device", device, "--overwrite"]
    if max_frames is not None:
        command += ["--max-frames", str(max_frames)]
    started = time.perf_counter()
    log = open(out.parent / f"{out.name}.log", "w")
    child = subprocess.Popen(command, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
    _, status, usage = os.wait4(child.pid, 0)
    seconds = time.perf_counter() - started
    log.close()
    row = {"method": method.name, "sequence": sequence.name, "exit_status": os.waitstatus_to_exitcode(status),
           "seconds": seconds, "peak_memory_mb": usage.ru_maxrss / 1024.0}
    metrics_path = out / "metrics.json"
    # A reconstruct's metrics (COLMAP's metrics.json has other keys, and no frame rate or rendering scores).
    # A failed run's folder may hold an earlier run's metrics.json: none of its figures are this run's.
    metrics = (read_metrics(metrics_path) if row["exit_status"] == 0 and method.command[0] == "reconstruct"
               and metrics_path.is_file() else None)
    # What the run itself recorded (a reconstruct without the mapper ran on the CPU); COLMAP always runs there.
    row["device"] = metrics.device.device if metrics is not None else (device if method.command[0] == "reconstruct" else "cpu")
    if metrics is not None and metrics.device.gpu is not None:
        row.update(gpu=metrics.device.gpu, gsplat_version=metrics.device.gsplat_version,
                   peak_gpu_memory_mb=metrics.device.peak_gpu_memory_mb)
    trajectory_path = out / "trajectory.txt"
    if row["exit_status"] == 0 and trajectory_path.is_file():
        ground_truth = read_tum_trajectory(sequence / "groundtruth.txt")
        errors = evaluate_trajectory(read_tum_trajectory(trajectory_path), ground_truth,
                                     align="sim3" if method.monocular else "se3")
        row.update(ate_cm=errors.ate_rmse_m * 100, rpe_cm=errors.rpe_trans_rmse_m * 100, poses=errors.pose_count)
    row.update(psnr_exported_db=None, ssim_exported=None, psnr_db=None, ssim=None, lpips=None)
    if metrics is not None and metrics.map is not None:
        # splats.ply as a viewer shows it first; then the run's own scores, through each view's exposure.
        exported, novel = metrics.map.rendering.novel_views_exported, metrics.map.rendering.novel_views
        row.update(psnr_exported_db=exported.psnr_db, ssim_exported=exported.ssim, psnr_db=novel.psnr_db, ssim=novel.ssim,
                   lpips=novel.lpips)
    row["fps"] = metrics.frames / seconds if metrics is not None else None
    row["outputs"] = sorted(p.name for p in out.iterdir() if p.is_file() and not p.name.startswith(".")) if out.is_dir() else []
    return row


def sequence_order(row: dict) -> tuple:
    """Rows of the whole TUM fr1/xyz first (the motion-capture benchmark), then by sequence name; methods keep
    their order."""
    names = [method.name for method in METHODS]
    method = names.index(row["method"]) if row["method"] in names else len(names)
    return (row["sequence"] != FR1_XYZ, row["sequence"], method)


def format_table(rows: list[dict]) -> str:
    """A Markdown table of the rows."""
    columns = [("sequence", "sequence", "{}"), ("method", "method", "{}"), ("ATE cm", "ate_cm", "{:.2f}"),
               ("RPE cm/frame", "rpe_cm", "{:.2f}"), ("PSNR dB as exported", "psnr_exported_db", "{:.2f}"),
               ("SSIM as exported", "ssim_exported", "{:.3f}"), ("PSNR dB with exposures", "psnr_db", "{:.2f}"),
               ("SSIM with exposures", "ssim", "{:.3f}"),
               ("LPIPS", "lpips", "{:.3f}"), ("frames/s", "fps", "{:.2f}"), ("peak MB", "peak_memory_mb", "{:.0f}"),
               ("device", "device", "{}"), ("outputs", "outputs", "{}")]
    lines = ["| " + " | ".join(title for title, _, _ in columns) + " |", "|" + "---|" * len(columns)]
    for row in rows:
        cells = []
        for _, key, form in columns:
            value = row.get(key)
            if row.get("exit_status", 0) != 0 and key == "outputs":
                cells.append(f"failed (exit {row['exit_status']})")
            elif value is None or value == []:
                cells.append("-")
            elif isinstance(value, list):
                cells.append(", ".join(value))
            else:
                cells.append(form.format(value))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def update_results_doc(result: dict) -> None:
    """Rewrite docs/benchmarks.md's section between the results markers: where, when and by which command the rows
    were measured (each row records its own), and the table."""
    document = ROOT / "docs" / "benchmarks.md"
    text = document.read_text()
    if RESULTS_START not in text:
        return
    head, rest = text.split(RESULTS_START, 1)
    _, tail = rest.split(RESULTS_END, 1)
    runs = dict.fromkeys((row.get("command", result["command"]), row.get("date", result["date"])[:10],
                          row.get("machine", result["machine"])) for row in result["rows"])
    measured = "; ".join(f"{date} on {machine} with `{command}`" for command, date, machine in runs)
    section = f"{RESULTS_START}\nMeasured {measured}:\n\n{format_table(result['rows'])}\n{RESULTS_END}"
    atomic_write_text(document, head + section + tail)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_data_argument(parser)
    parser.add_argument("--quick", action="store_true", help="first 100 frames of each sequence")
    parser.add_argument("--gpu", action="store_true",
                        help="tambridge runs map on CUDA with gsplat (--device cuda); stops at once when there is no GPU")
    parser.add_argument("--methods", nargs="*", help="subset of method names")
    parser.add_argument("--sequences", nargs="*", help="subset of sequence folder names (or paths)")
    parser.add_argument("--no-doc", action="store_true", help="do not rewrite docs/benchmarks.md's results section")
    parser.add_argument("--doc-only", action="store_true",
                        help="run nothing: regenerate docs/benchmarks.md's results section from benchmarks/results/run_all.json")
    arguments = parser.parse_args()
    results_path = ROOT / "benchmarks" / "results" / "run_all.json"
    if arguments.doc_only:
        result = json.loads(results_path.read_text())
        update_results_doc(result)
        return
    gpu = None
    if arguments.gpu:
        # Checked here, before any run: a --gpu table must not quietly hold CPU runs.
        import torch

        from tambridge.errors import ConfigError
        from tambridge.device import resolve_device

        try:
            gpu = torch.cuda.get_device_name(resolve_device("cuda"))
        except ConfigError as error:
            parser.exit(2, f"run_all.py --gpu: {error}\n(without --gpu every method runs on the CPU)\n")
    if arguments.sequences:  # every one found before any run
        sequences = [find_sequence(name, arguments.data) for name in arguments.sequences]
    else:
        sequences = sequences_with_ground_truth(arguments.data)
    max_frames = 100 if arguments.quick else None
    runs = ROOT / "benchmarks" / "results" / "runs"
    runs.mkdir(parents=True, exist_ok=True)
    rows = []
    # Frames/s on a shared 2-core machine depend on what else runs: the machine line says so.
    load_at_start = os.getloadavg()[0]
    command = " ".join(["python", "benchmarks/run_all.py", *sys.argv[1:]])
    for sequence in sequences:
        for method in METHODS:
            if arguments.methods and method.name not in arguments.methods:
                continue
            if not method.registered_colour and camera_file_for(sequence) is None:
                continue  # its colour is registered: the same run as the default
            out = runs / f"{sequence.name}__{method.name.split(' (')[0].replace(' ', '_')}"
            print(f"running {method.name} on {sequence.name} ...", flush=True)
            row = run_method(method, sequence, out, max_frames, "cuda" if arguments.gpu else "cpu")
            rows.append(row | {"date": datetime.datetime.now().isoformat(timespec="seconds"), "command": command})
    print(format_table(rows))
    machine = f"{describe_machine(gpu)} (1-minute load average {load_at_start:.1f} at the start, {os.getloadavg()[0]:.1f} at the end)"
    rows = [row | {"machine": machine} for row in rows]
    if arguments.sequences or arguments.methods:  # a subset: the other rows stay, with their own date and command
        old = json.loads(results_path.read_text()) if results_path.is_file() else {"rows": []}
        earlier = [{"date": old["date"], "command": old["command"], "machine": old["machine"]} | row for row in old["rows"]]
        rows = merge_rows(earlier, rows, ("sequence", "method"))
    result = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "machine": machine, "command": command,
              "rows": sorted(rows, key=sequence_order)}
    atomic_write_text(results_path, json.dumps(result, indent=2) + "\n")
    if not arguments.no_doc:
        update_results_doc(result)


if __name__ == "__main__":
    main()
