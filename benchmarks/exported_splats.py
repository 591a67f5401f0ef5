"""What a user's viewer shows: the map as exported (splats.ply) against the run's exposure-compensated scores.

    python benchmarks/exported_splats.py /work/data/rgbd_dataset_freiburg1_xyz --max-frames 200
    python benchmarks/exported_splats.py SEQ1 SEQ2 --preset default --preset quality

Every (sequence, preset) is one ``reconstruct`` run in its own process (under benchmarks/results/runs/), mesh off.
The figures are those of its metrics.json: novel views (every 5th frame that is not a mapping view) scored
through each view's exposure from the rendering poses (the run's own scores) and as exported (splats.ply
reloaded, no exposure, trajectory.txt's poses), all at full resolution; ``SSIM map res`` is the as-exported SSIM
with render and frame area-averaged to the mapping resolution; the colour ratios are mean render / mean frame as
exported at the first and last mapping view (mean of R, G, B; 1: true colour). A sequence with a camera file in
benchmarks/sequences.py (7-Scenes) is read with it.

Where the as-exported score stops: the same renders after the per-channel affine colour map (gain, bias) that fits
all of them best at once (``PSNR best bake``: the most any colour baked into the file could give) and after the
one fitted to each frame itself (``PSNR per-frame fit``: an oracle of every frame's exposure, which no static
file can hold). Prints a table and writes benchmarks/results/exported_splats.json.
"""

from __future__ import annotations

import argparse
import datetime
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import describe_machine  # noqa: E402
from benchmarks.sequences import camera_file_for  # noqa: E402
from tambridge.config import load_config  # noqa: E402
from tambridge.evaluation.exported import ExportedMap  # noqa: E402
from tambridge.evaluation.metrics import read_metrics  # noqa: E402
from tambridge.evaluation.rendering import psnr_db, score_frames  # noqa: E402
from tambridge.files import atomic_write_text  # noqa: E402
from tambridge.gaussians.mapper import affine_colour_fit  # noqa: E402
from tambridge.io.tum import open_sequence  # noqa: E402
from tambridge.threads import TORCH_THREADS, compute_threads  # noqa: E402
from tambridge.trajectory import read_tum_trajectory  # noqa: E402

RESULT = ROOT / "benchmarks" / "results" / "exported_splats.json"


def run_case(sequence: Path, preset: str, max_frames: int | None, settings: list[str]) -> dict:
    """One ``reconstruct`` run of ``sequence`` with ``preset`` in a child process; returns its row."""
    out = ROOT / "benchmarks" / "results" / "runs" / f"exported__{sequence.name}__{preset}__{max_frames or 'all'}"
    camera = camera_file_for(sequence)
    command = [sys.executable, str(ROOT / "cli.py"), "reconstruct", str(sequence), "-o", str(out), "--quiet",
               "--overwrite", "--config", str(ROOT / "configs" / f"{preset}.yaml"), "--set", "mesh.enabled=false",
               *(["--camera", str(camera)] if camera is not None else []),
               *(["--max-frames", str(max_frames)] if max_frames else []),
               *[argument for setting in settings for argument in ("--set", setting)]]
    out.parent.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    with open(out.parent / f"{out.name}.log", "w") as log:
        status = subprocess.run(command, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT).returncode
    row = {"sequence": sequence.name, "preset": preset, "settings": settings, "exit_status": status,
           "wall_seconds": time.perf_counter() - started}
    if status != 0 or not (out / "metrics.json").is_file():
        return row
    metrics = read_metrics(out / "metrics.json")
    row.update(frames=metrics.frames, fps=metrics.fps_end_to_end)
    if metrics.map is not None:
        compensated, exported = metrics.map.rendering.novel_views, metrics.map.rendering.novel_views_exported
        row.update(compensated_psnr_db=compensated.psnr_db, compensated_ssim=compensated.ssim,
                   exported_psnr_db=exported.psnr_db, exported_ssim=exported.ssim,
                   exported_ssim_mapping_resolution=exported.ssim_mapping_resolution,
                   first_view_colour_ratio=exported.first_view_colour_ratio,
                   last_view_colour_ratio=exported.last_view_colour_ratio, gaussians=metrics.map.gaussians,
                   novel_frames=compensated.frames, **colour_bounds(out, sequence, camera, max_frames))
    return row


def colour_bounds(run_dir: Path, sequence_dir: Path, camera: Path | None, max_frames: int | None) -> dict:
    """As-exported PSNR of the run's novel-view candidates (every 5th frame that is no keyframe) as rendered, after
    the best affine colour map for all of them at once, and after the best for each frame alone."""
    sequence = open_sequence(sequence_dir, camera_file=camera, max_frames=max_frames)
    config = load_config(run_dir / "config.yaml")
    exported = ExportedMap.from_run(run_dir, config.mapper)
    keyframe_times = read_tum_trajectory(run_dir / "keyframes.txt").timestamps_s
    frames = [index for index in range(0, len(sequence), config.evaluation.novel_view_every)
              if np.min(np.abs(keyframe_times - sequence.timestamps_s[index])) > 1e-6]
    if not frames:
        return {"bound_frames": 0}
    with compute_threads(TORCH_THREADS, config.mapper.kernel_threads):
        pairs = [(rendered, observed) for _, rendered, observed in
                 score_frames(sequence, lambda index: exported.render(sequence.camera, index).rgb, frames)]
    pooled = _affine_fit(np.concatenate([r.reshape(-1, 3) for r, _ in pairs]), np.concatenate([o.reshape(-1, 3) for _, o in pairs]))
    return {
        "bound_frames": len(frames),
        "exported_psnr_db_as_written": float(np.mean([psnr_db(r, o) for r, o in pairs])),
        "exported_psnr_db_best_bake": float(np.mean([psnr_db(np.clip(r * pooled[0] + pooled[1], 0, 1), o) for r, o in pairs])),
        "exported_psnr_db_per_frame_fit": float(np.mean([psnr_db(np.clip(r * fit[0] + fit[1], 0, 1), o) for r, o in pairs
                                                         for fit in [_affine_fit(r.reshape(-1, 3), o.reshape(-1, 3))]])),
        "best_bake_gain_bias": pooled.tolist(),
    }


def _affine_fit(rendered: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """(2, 3): per channel, the gain and bias that map ``rendered`` (M, 3) closest to ``observed`` (M, 3) (least
    squares, :func:`tambridge.gaussians.mapper.affine_colour_fit`)."""
    return torch.stack(affine_colour_fit(torch.from_numpy(rendered), torch.from_numpy(observed))).numpy()


def _mean(ratio: list[float] | None) -> float | None:
    return None if ratio is None else sum(ratio) / len(ratio)


def format_table(rows: list[dict]) -> str:
    """A Markdown table of the rows."""
    columns = ["sequence", "preset", "settings", "PSNR compensated", "PSNR exported", "gap dB", "SSIM compensated",
               "SSIM exported", "SSIM map res", "colour first", "colour last", "PSNR best bake", "PSNR per-frame fit",
               "fps", "Gaussians"]
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for row in rows:
        if "exported_psnr_db" not in row:
            lines.append(f"| {row['sequence']} | {row['preset']} | {' '.join(row['settings'])} | failed (exit "
                         f"{row['exit_status']}) |" + " |" * (len(columns) - 4))
            continue
        number = lambda value, form: "-" if value is None else form.format(value)  # noqa: E731
        gap = (None if row["compensated_psnr_db"] is None or row["exported_psnr_db"] is None
               else row["exported_psnr_db"] - row["compensated_psnr_db"])
        cells = [row["sequence"], row["preset"], " ".join(row["settings"]) or "-",
                 number(row["compensated_psnr_db"], "{:.2f}"), number(row["exported_psnr_db"], "{:.2f}"),
                 number(gap, "{:+.2f}"), number(row["compensated_ssim"], "{:.3f}"), number(row["exported_ssim"], "{:.3f}"),
                 number(row["exported_ssim_mapping_resolution"], "{:.3f}"),
                 number(_mean(row["first_view_colour_ratio"]), "{:.3f}"), number(_mean(row["last_view_colour_ratio"]), "{:.3f}"),
                 number(row.get("exported_psnr_db_best_bake"), "{:.2f}"), number(row.get("exported_psnr_db_per_frame_fit"), "{:.2f}"), number(row["fps"], "{:.2f}"), str(row["gaussians"])]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sequences", nargs="+", type=Path, help="TUM-layout sequence folders")
    parser.add_argument("--max-frames", type=int, default=0, help="frames of each sequence to use (0: all)")
    parser.add_argument("--preset", action="append", help="configs/PRESET.yaml (repeatable; default: default)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a config override for every run (repeatable), e.g. mapper.exposure_prior=0")
    arguments = parser.parse_args()
    rows = []
    for sequence in arguments.sequences:
        for preset in arguments.preset or ["default"]:
            print(f"running {preset} on {sequence.name} ...", flush=True)
            rows.append(run_case(sequence, preset, arguments.max_frames or None, arguments.set))
    print(format_table(rows))
    machine = describe_machine()
    command = " ".join(["python", "benchmarks/exported_splats.py", *sys.argv[1:]])
    for row in rows:
        row.update(date=datetime.datetime.now().isoformat(timespec="seconds"), machine=machine, command=command)
    # Rows of other cases (sequences, presets, settings, lengths) from earlier invocations are kept.
    case = lambda row: (row["sequence"], row["preset"], row["settings"], row.get("frames"))  # noqa: E731
    new = {json.dumps(case(row)) for row in rows}
    kept = [row for row in json.loads(RESULT.read_text())["rows"] if json.dumps(case(row)) not in new] if RESULT.is_file() else []
    atomic_write_text(RESULT, json.dumps({"rows": kept + rows}, indent=2) + "\n")


if __name__ == "__main__":
    main()
