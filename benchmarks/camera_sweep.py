"""How the camera model moves a trajectory's error and scale: tracking with the camera file's focal lengths changed.

    python benchmarks/camera_sweep.py                                  # 7-Scenes 0-699, colour focal x0.976 ... x1.048
    python benchmarks/camera_sweep.py --colour-focal-factors 1 1.05 --depth-fx 570 585 600 615 630

7-Scenes is read with `configs/cameras/7scenes_kinect.yaml`: its depth camera's focal length is the dataset's
published 585 px (no calibration of this Kinect confirms it), and its colour camera, into which colour is resampled,
was fitted to the images' edges by `fit_colour_registration.py`. Each setting changes one of them, all else kept:
``--colour-focal-factors`` multiplies ``colour_fx`` and ``colour_fy``, ``--depth-fx`` sets the depth camera's
``fx = fy``. The default pipeline then tracks the sequence (``tambridge reconstruct --set mapper.enabled=false --set
mesh.enabled=false --set frontend.orb.mapping_thread=false``: inline, so each run repeats to the bit). Each row:
ATE after an SE(3) and after a Sim(3) alignment to the ground truth (7-Scenes: KinectFusion's, a pseudo ground
truth), the Sim(3) scale (what the estimate is multiplied by to fit it) and RPE. Where the SE(3) ATE falls while the
Sim(3) ATE stays, the setting moves the trajectory's scale and little else.

The table goes to stdout, the rows to benchmarks/results/camera_sweep.json.
"""

from __future__ import annotations

import argparse
import datetime
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import describe_machine  # noqa: E402
from benchmarks.sequences import KITCHEN, add_sequence_arguments, camera_file_for, find_sequence  # noqa: E402
from tambridge.files import atomic_write_text  # noqa: E402
from tambridge.trajectory import Trajectory, read_tum_trajectory  # noqa: E402

DEFAULT_COLOUR_FOCAL_FACTORS = (0.976, 0.988, 1.0, 1.012, 1.024, 1.048)
TRACKING_ONLY = ("mapper.enabled=false", "mesh.enabled=false", "frontend.orb.mapping_thread=false")


def changed_camera_values(camera_file: Path, colour_focal_factor: float = 1.0, depth_fx: float | None = None) -> dict:
    """The values of ``camera_file`` with the colour camera's focal lengths times ``colour_focal_factor`` and the depth
    camera's ``fx = fy = depth_fx`` (None: as it is)."""
    values = yaml.safe_load(Path(camera_file).read_text())
    if colour_focal_factor != 1.0:
        if "colour_fx" not in values or "colour_fy" not in values:
            raise SystemExit(f"error: {camera_file}: has no colour camera (colour_fx, colour_fy) to scale")
        values["colour_fx"] = float(values["colour_fx"]) * colour_focal_factor
        values["colour_fy"] = float(values["colour_fy"]) * colour_focal_factor
    if depth_fx is not None:
        values["fx"] = values["fy"] = float(depth_fx)
    return values


def tracked_row(folder: Path, reference: Trajectory, camera_values: dict, setting: str) -> dict:
    """Track ``folder`` with a camera file of ``camera_values``; its errors against ``reference`` (the folder's
    ground truth), under ``setting`` (the row's name)."""
    from tambridge.evaluation.trajectory import evaluate_trajectory

    with tempfile.TemporaryDirectory() as scratch:
        camera_file = Path(scratch) / "camera.yaml"
        camera_file.write_text(yaml.safe_dump(camera_values, sort_keys=False))
        output = Path(scratch) / "run"
        command = [sys.executable, str(ROOT / "cli.py"), "reconstruct", str(folder), "-o", str(output), "--quiet",
                   "--camera", str(camera_file), *[argument for option in TRACKING_ONLY for argument in ("--set", option)]]
        child = subprocess.run(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        if child.returncode != 0:
            last = (child.stderr.strip().splitlines() or ["no message"])[-1]
            raise SystemExit(f"error: {folder}: the run with {setting} failed (exit {child.returncode}): {last}")
        estimate = read_tum_trajectory(output / "trajectory.txt")
    rigid = evaluate_trajectory(estimate, reference, align="se3")
    similar = evaluate_trajectory(estimate, reference, align="sim3")
    return {"setting": setting, "fx_px": camera_values["fx"], "colour_fx_px": camera_values.get("colour_fx"),
            "ate_se3_cm": 100 * rigid.ate_rmse_m, "ate_sim3_cm": 100 * similar.ate_rmse_m, "sim3_scale": similar.scale,
            "rpe_cm_per_frame": 100 * rigid.rpe_trans_rmse_m}


def format_table(rows: list[dict]) -> str:
    lines = ["| setting | depth fx px | colour fx px | ATE SE(3) cm | ATE Sim(3) cm | Sim(3) scale | RPE cm/frame |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {row['setting']} | {row['fx_px']:.1f} | "
              f"{'-' if row['colour_fx_px'] is None else format(row['colour_fx_px'], '.1f')} | {row['ate_se3_cm']:.3f} | "
              f"{row['ate_sim3_cm']:.3f} | {row['sim3_scale']:.4f} | {row['rpe_cm_per_frame']:.3f} |" for row in rows]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_sequence_arguments(parser, KITCHEN)
    parser.add_argument("--colour-focal-factors", type=float, nargs="*", default=list(DEFAULT_COLOUR_FOCAL_FACTORS))
    parser.add_argument("--depth-fx", type=float, nargs="*", default=[], help="depth camera fx = fy values, px")
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks" / "results" / "camera_sweep.json")
    args = parser.parse_args()
    if any(value <= 0 for value in (*args.colour_focal_factors, *args.depth_fx)):
        raise SystemExit("error: --colour-focal-factors and --depth-fx take positive values")
    if not args.colour_focal_factors and not args.depth_fx:
        raise SystemExit("error: nothing to sweep; give --colour-focal-factors or --depth-fx values")
    folder = find_sequence(args.sequence, args.data)
    camera_file = camera_file_for(folder)
    if camera_file is None:
        raise SystemExit(f"error: {folder.name}: no camera file to change; add one to CAMERA_FILES in "
                         "benchmarks/sequences.py")
    # Read once, before any run: a folder without ground truth stops here.
    if not (folder / "groundtruth.txt").is_file():
        raise SystemExit(f"error: {folder}: has no groundtruth.txt; the sweep scores each run against it")
    reference = read_tum_trajectory(folder / "groundtruth.txt")
    settings = [(f"colour focal x{factor:g}", changed_camera_values(camera_file, colour_focal_factor=factor))
                for factor in args.colour_focal_factors]
    settings += [(f"depth fx {fx:g} px", changed_camera_values(camera_file, depth_fx=fx)) for fx in args.depth_fx]
    rows = [tracked_row(folder, reference, values, setting) for setting, values in settings]
    print(format_table(rows))
    document = {"sequence": folder.name, "camera_file": str(camera_file.relative_to(ROOT)), "rows": rows,
                "date": datetime.datetime.now().isoformat(timespec="seconds"),
                "command": " ".join(["python", "benchmarks/camera_sweep.py", *sys.argv[1:]]),
                "machine": describe_machine()}
    atomic_write_text(args.output, json.dumps(document, indent=2) + "\n")


if __name__ == "__main__":
    main()
