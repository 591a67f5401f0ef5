"""Fusion Bridge on vs off, default vs fast preset: rendering quality and speed of ``tambridge reconstruct``.

    python benchmarks/reconstruct.py                         # 7-Scenes (first 150 frames) + a synthetic loop
    python benchmarks/reconstruct.py --max-frames 0          # all 700 7-Scenes frames
    python benchmarks/reconstruct.py --sequences rgbd_dataset_freiburg1_xyz --max-frames 0 --skip-synthetic

Real sequences are named by folder (``--sequences``, default 7-Scenes redkitchen) and looked for in the ``--data``
folders (default: ``shared/data`` and ``data`` beside the repository); one that is missing stops the run at once
with a line saying how to get it. ``--max-frames`` applies to each real sequence.

Every case is one ``reconstruct`` run in its own process (peak memory = that process's ru_maxrss, read with
wait4), written under benchmarks/results/runs/. Rendering scores are those of metrics.json: renders at full
resolution from the rendering poses against the input frames, on every 5th frame that is not a mapping view
("novel") and on the mapping views. ``fps`` is metrics.json's end-to-end rate (read, tracking, bridge, mapping,
final pass, export; the rendering evaluation is not part of it); ``wall fps`` counts the whole process.
7-Scenes is read with colour resampled into the depth camera (benchmarks/sequences.py). The synthetic sequence is a 320x240 anti-aliased loop with exact registered depth (see SYNTHETIC below).
Prints a table and writes benchmarks/results/reconstruct.json.
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
from benchmarks.sequences import KITCHEN, add_data_argument, camera_file_for, find_sequence, merge_rows  # noqa: E402
from tambridge.config import load_config  # noqa: E402
from tambridge.evaluation.metrics import read_metrics  # noqa: E402
from tambridge.files import atomic_write_text  # noqa: E402
from tambridge.io.synthetic import SynthOptions, write_synthetic_sequence  # noqa: E402

PRESETS = ("default", "fast")
# 320x240 with 3 x 3 rays per pixel (anti-aliased, as a camera integrates over its pixels; slow to write, so it
# is written once and kept under benchmarks/results/runs/).
SYNTHETIC = SynthOptions(frame_count=120, width=320, height=240, seed=0, supersampling=3)
# The synthetic depth is registered to colour and exact up to its 1/5000 m steps, so the ORB frontend's RGB-D
# residuals are on, with a small depth noise.
SYNTHETIC_SETTINGS = ["--set", "frontend.orb.depth_residuals=true", "--set", "frontend.orb.depth_noise_per_m=0.003"]


def synthetic_mapping_scale(preset: str) -> list[str]:
    """The preset's mapping resolution scale doubled: the 320x240 synthetic frames are then mapped at the image size
    a 640x480 camera is mapped at (default 160x120, fast 80x60)."""
    scale = load_config(ROOT / "configs" / f"{preset}.yaml").mapper.resolution_scale
    return ["--set", f"mapper.resolution_scale={2.0 * scale:g}"]


def run_case(sequence: Path, preset: str, bridge: bool, out: Path, max_frames: int | None, extra: list[str]) -> dict:
    """One ``reconstruct`` run in a child process; returns its row."""
    command = [sys.executable, str(ROOT / "cli.py"), "reconstruct", str(sequence), "-o", str(out), "--quiet",
               "--config", str(ROOT / "configs" / f"{preset}.yaml"), "--set", f"bridge.enabled={str(bridge).lower()}",
               "--set", "mesh.enabled=false", *extra]
    if max_frames:
        command += ["--max-frames", str(max_frames)]
    out.parent.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    with open(out.parent / f"{out.name}.log", "w") as log:
        child = subprocess.Popen(command, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(child.pid, 0)
    seconds = time.perf_counter() - started
    row = {"sequence": sequence.name, "preset": preset, "bridge": bridge, "exit_status": os.waitstatus_to_exitcode(status),
           "wall_seconds": seconds, "peak_memory_mb": usage.ru_maxrss / 1024.0, "extra": extra}
    metrics_path = out / "metrics.json"
    if not metrics_path.is_file():
        return row
    metrics = read_metrics(metrics_path)
    row.update(frames=metrics.frames, fps=metrics.fps_end_to_end, wall_fps=metrics.frames / seconds,
               seconds_per_stage=metrics.seconds_per_stage,
               ate_cm=metrics.trajectory.ate_rmse_m * 100 if metrics.trajectory is not None else float("nan"))
    if metrics.map is not None:
        novel, views = metrics.map.rendering.novel_views, metrics.map.rendering.mapping_views
        views_ate = metrics.map.bridge.views_ate_rmse_m
        row.update(
            novel_psnr_db=novel.psnr_db, novel_ssim=novel.ssim, novel_lpips=novel.lpips, novel_frames=novel.frames,
            views_psnr_db=views.psnr_db, views_ssim=views.ssim, mapping_views=metrics.map.mapping_views,
            gaussians=metrics.map.gaussians,
            views_ate_frontend_cm=views_ate.frontend * 100 if views_ate is not None else float("nan"),
            views_ate_rendering_cm=views_ate.rendering * 100 if views_ate is not None else float("nan"),
        )
    return row


def format_table(rows: list[dict]) -> str:
    """A Markdown table of the rows."""
    columns = [("sequence", "sequence", "{}"), ("preset", "preset", "{}"), ("bridge", "bridge", "{}"),
               ("novel PSNR", "novel_psnr_db", "{:.2f}"), ("novel SSIM", "novel_ssim", "{:.3f}"),
               ("LPIPS", "novel_lpips", "{:.3f}"), ("views PSNR", "views_psnr_db", "{:.2f}"),
               ("views SSIM", "views_ssim", "{:.3f}"), ("views", "mapping_views", "{}"), ("Gaussians", "gaussians", "{}"),
               ("views ATE cm (frontend -> rendering)", "views_ate", "{}"), ("fps", "fps", "{:.2f}"),
               ("wall fps", "wall_fps", "{:.2f}"), ("peak MB", "peak_memory_mb", "{:.0f}")]
    lines = ["| " + " | ".join(title for title, _, _ in columns) + " |", "|" + "---|" * len(columns)]
    for row in rows:
        cells = []
        for _, key, form in columns:
            if key == "views_ate":
                value = f"{row.get('views_ate_frontend_cm', float('nan')):.2f} -> {row.get('views_ate_rendering_cm', float('nan')):.2f}"
            else:
                value = row.get(key)
            if row.get("exit_status", 0) != 0 and key == "novel_psnr_db":
                cells.append(f"failed (exit {row['exit_status']})")
            elif value is None:
                cells.append("-")
            else:
                cells.append(form.format(value) if not isinstance(value, str) else value)
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def bridge_gains(rows: list[dict]) -> list[dict]:
    """Novel-view PSNR of bridge on minus bridge off, per sequence and preset."""
    gains = []
    for sequence in dict.fromkeys(row["sequence"] for row in rows):
        for preset in PRESETS:
            on = [r for r in rows if r["sequence"] == sequence and r["preset"] == preset and r["bridge"]]
            off = [r for r in rows if r["sequence"] == sequence and r["preset"] == preset and not r["bridge"]]
            if on and off and on[0].get("novel_psnr_db") is not None and off[0].get("novel_psnr_db") is not None:
                gains.append({"sequence": sequence, "preset": preset,
                              "novel_psnr_gain_db": on[0]["novel_psnr_db"] - off[0]["novel_psnr_db"]})
    return gains


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_data_argument(parser)
    parser.add_argument("--sequences", nargs="*", default=[KITCHEN], help="real sequences: folder names (or paths)")
    parser.add_argument("--max-frames", type=int, default=150, help="frames of each real sequence (0: all)")
    parser.add_argument("--presets", nargs="*", default=list(PRESETS))
    parser.add_argument("--skip-synthetic", action="store_true")
    arguments = parser.parse_args()
    runs = ROOT / "benchmarks" / "results" / "runs"
    # (sequence, frames, settings, whether its frames are 320x240 synthetic ones); every folder found before any run.
    cases = []
    for folder in [find_sequence(name, arguments.data) for name in arguments.sequences]:
        camera_file = camera_file_for(folder)
        cases.append((folder, arguments.max_frames or None, [] if camera_file is None else ["--camera", str(camera_file)],
                      False))
    if not arguments.skip_synthetic:
        synthetic = runs / "synthetic_loop_120_320x240_ss3"
        if not (synthetic / "groundtruth.txt").is_file():
            write_synthetic_sequence(synthetic, SYNTHETIC)
        cases.append((synthetic, None, SYNTHETIC_SETTINGS, True))
    rows = []
    for sequence, max_frames, extra, is_synthetic in cases:
        for preset in arguments.presets:
            settings = extra + (synthetic_mapping_scale(preset) if is_synthetic else [])
            for bridge in (True, False):
                out = runs / f"{sequence.name}__{preset}__bridge_{'on' if bridge else 'off'}"
                print(f"running {preset}, bridge {'on' if bridge else 'off'} on {sequence.name} ...", flush=True)
                rows.append(run_case(sequence, preset, bridge, out, max_frames, settings) | {"max_frames": max_frames})
    table = format_table(rows)
    gains = bridge_gains(rows)
    print(table)
    for gain in gains:
        print(f"bridge gain, {gain['sequence']} {gain['preset']}: {gain['novel_psnr_gain_db']:+.2f} dB novel-view PSNR")
    machine = describe_machine()
    command = " ".join(["python", "benchmarks/reconstruct.py", *sys.argv[1:]])
    date = datetime.datetime.now().isoformat(timespec="seconds")
    rows = [row | {"date": date, "command": command} for row in rows]
    # Rows of sequences, presets and bridge settings not run this time stay (with the earlier run's date).
    path = ROOT / "benchmarks" / "results" / "reconstruct.json"
    old = json.loads(path.read_text()) if path.is_file() else {"rows": []}
    earlier = [{"date": old["date"], "command": old["command"]} | row for row in old["rows"]]
    rows = merge_rows(earlier, rows, ("sequence", "preset", "bridge"))
    result = {"date": date, "machine": machine, "command": command, "rows": rows, "bridge_gains": bridge_gains(rows)}
    atomic_write_text(path, json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
