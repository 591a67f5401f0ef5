"""A motion-blurred synthetic sequence with exact sharp ground truth: what blur costs tracking and the map.

    python benchmarks/blurred_synthetic.py                   # default preset, bridge on
    python benchmarks/blurred_synthetic.py --bridge-off-too  # and bridge off
    python benchmarks/blurred_synthetic.py --sharp-sequence DIR  # and the same path without blur

The sequence is the issue-23 one: the 120-frame 320x240 synthetic loop, each colour frame the mean of sharp renders
over a 1/30 s exposure along the true path, with two 1.5 s bursts of fast rotation (90 deg/s tilts), and the sharp
frames in gt_rgb/ (written once under benchmarks/results/runs/). Each case is one ``reconstruct`` run in its own
process (benchmarks/reconstruct.py's run_case, with its synthetic settings). Reported from metrics.json: novel-view
PSNR against the sharp frames and against the blurred inputs, on the sharper half of the novel views, the ATE, and
tracking (frames lost); from trajectory.txt the ATE of the frames inside the bursts and outside them.
Prints a table and writes benchmarks/results/blurred_synthetic.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import describe_machine  # noqa: E402
from benchmarks.reconstruct import SYNTHETIC_SETTINGS, run_case, synthetic_mapping_scale  # noqa: E402
from tambridge.evaluation.metrics import read_metrics  # noqa: E402
from tambridge.evaluation.trajectory import evaluate_trajectory  # noqa: E402
from tambridge.files import atomic_write_text  # noqa: E402
from tambridge.io.synthetic import RotationBursts, SynthOptions, write_synthetic_sequence  # noqa: E402
from tambridge.trajectory import read_tum_trajectory  # noqa: E402

BLURRED = SynthOptions(frame_count=120, width=320, height=240, exposure_s=1.0 / 30.0, bursts=RotationBursts(count=2))


def burst_ate_cm(run_dir: Path, sequence: Path) -> dict:
    """ATE RMSE (cm, SE(3)-aligned over the whole run) of the frames inside the rotation bursts and outside them."""
    errors = evaluate_trajectory(read_tum_trajectory(run_dir / "trajectory.txt"),
                                 read_tum_trajectory(sequence / "groundtruth.txt"), "se3")
    inside = np.zeros(len(errors.timestamps_s), bool)
    for start_s, end_s in BLURRED.bursts.windows_s(BLURRED.frame_count / BLURRED.fps):
        inside |= (errors.timestamps_s >= start_s) & (errors.timestamps_s <= end_s)
    rmse = lambda values: float(np.sqrt(np.mean(values**2)) * 100) if len(values) else None  # noqa: E731
    return {"ate_in_bursts_cm": rmse(errors.ate_errors_m[inside]), "ate_outside_bursts_cm": rmse(errors.ate_errors_m[~inside]),
            "poses_in_bursts": int(inside.sum())}


def blur_row(row: dict, run_dir: Path, sequence: Path) -> dict:
    """The run's row with the blur figures of its metrics.json and trajectory."""
    if row["exit_status"] != 0:
        return row
    metrics = read_metrics(run_dir / "metrics.json")
    row.update(frames_lost=metrics.frames_lost, frames_relocalised=metrics.frames_relocalised,
               tracked_share=1.0 - metrics.frames_lost / metrics.frames)
    if metrics.map is not None:
        rendering = metrics.map.rendering
        # Sharp inputs (no gt_rgb/) are their own sharp ground truth.
        against_input = rendering.novel_views_against_input or rendering.novel_views
        row.update(blurred=rendering.scored_against == "sharp_ground_truth",
                   novel_psnr_sharp_db=rendering.novel_views.psnr_db, novel_psnr_input_db=against_input.psnr_db,
                   novel_ssim_sharp=rendering.novel_views.ssim, novel_ssim_input=against_input.ssim,
                   novel_psnr_sharper_half_db=rendering.novel_views_sharper_half.psnr_db,
                   sharper_half_frames=rendering.novel_views_sharper_half.frames,
                   view_selection=metrics.map.bridge.view_selection)
    row.update(burst_ate_cm(run_dir, sequence))
    return row


def format_table(rows: list[dict]) -> str:
    columns = [("inputs blurred", "blurred", "{}"), ("bridge", "bridge", "{}"), ("novel PSNR vs sharp", "novel_psnr_sharp_db", "{:.2f}"),
               ("novel PSNR vs blurred input", "novel_psnr_input_db", "{:.2f}"),
               ("sharper half vs sharp", "novel_psnr_sharper_half_db", "{:.2f}"), ("ATE cm", "ate_cm", "{:.2f}"),
               ("ATE in bursts cm", "ate_in_bursts_cm", "{:.2f}"), ("ATE outside cm", "ate_outside_bursts_cm", "{:.2f}"),
               ("frames lost", "frames_lost", "{}"), ("views", "mapping_views", "{}"), ("fps", "fps", "{:.2f}")]
    lines = ["| " + " | ".join(title for title, _, _ in columns) + " |", "|" + "---|" * len(columns)]
    for row in rows:
        cells = [("-" if row.get(key) is None else form.format(row[key])) for _, key, form in columns]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="default")
    parser.add_argument("--bridge-off-too", action="store_true")
    parser.add_argument("--sequence", type=Path, help="A copy of the sequence already written (tambridge synth DIR "
                        "--frames 120 --size 320x240 --motion-blur 0.0333 --rotation-bursts 2); default: write one")
    parser.add_argument("--sharp-sequence", type=Path, help="Also run on the same path without blur (tambridge synth "
                        "DIR --frames 120 --size 320x240 --rotation-bursts 2): what the blur costs")
    arguments = parser.parse_args()
    runs = ROOT / "benchmarks" / "results" / "runs"
    sequence = arguments.sequence or runs / "synthetic_blurred_120_320x240_exp33ms_2bursts"
    if not (sequence / "groundtruth.txt").is_file():
        print(f"writing {sequence.name} ...", flush=True)
        write_synthetic_sequence(sequence, BLURRED)
    # --overwrite: a repeated benchmark replaces its earlier runs rather than being refused by them.
    settings = SYNTHETIC_SETTINGS + synthetic_mapping_scale(arguments.preset) + ["--overwrite"]
    cases = [(sequence, bridge) for bridge in ((True, False) if arguments.bridge_off_too else (True,))]
    if arguments.sharp_sequence:
        cases.append((arguments.sharp_sequence, True))
    rows = []
    for folder, bridge in cases:
        out = runs / f"{folder.name}__{arguments.preset}__bridge_{'on' if bridge else 'off'}"
        print(f"running {arguments.preset}, bridge {'on' if bridge else 'off'} on {folder.name} ...", flush=True)
        rows.append(blur_row(run_case(folder, arguments.preset, bridge, out, None, settings), out, folder))
    print(format_table(rows))
    machine = describe_machine()
    result = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "machine": machine,
              "command": " ".join(["python", "benchmarks/blurred_synthetic.py", *sys.argv[1:]]),
              "sequence": {"frames": BLURRED.frame_count, "size": [BLURRED.width, BLURRED.height],
                           "exposure_s": BLURRED.exposure_s, "bursts": dataclasses.asdict(BLURRED.bursts)},
              "rows": rows}
    atomic_write_text(ROOT / "benchmarks" / "results" / "blurred_synthetic.json", json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
