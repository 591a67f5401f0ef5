"""The trajectory smoothed under a motion model (``frontend.smoothing``): nearer the ground truth, and what the map
looks like from it.

    python benchmarks/smoothing.py /work/data/rgbd_dataset_freiburg1_xyz /work/shared/data/tum_fr1_xyz_first37

Each sequence is reconstructed once with the default preset but smoothing off (and mesh off) in its own process,
under benchmarks/results/runs/. Its trajectory.txt (the tracked poses) is then smoothed about the run's keyframes
(keyframes.txt) with the default motion model, as a default run writes it. Both
are scored against the ground truth (SE(3) ATE, largest error, RPE per frame) and the run's splats.ply is rendered
at both, with no exposure, at every 5th frame that is not a keyframe (full resolution; PSNR and SSIM as the run's
as-exported scores compute them): the same map seen from the two trajectories. The map is rendered a third time
from the ground truth itself, interpolated at the frame times and moved into the run's world by the SE(3) that
fits it to the tracked poses: on a synthetic sequence, whose ground truth is exact, this says whether the score
of a render judges a trajectory or only its agreement with the poses the map was built from. A fourth row keeps
the smoothing's change only along the image's translation-rotation ambiguity at each frame's median depth
(:func:`~tambridge.frontend.smoothing.along_image_ambiguity`). Prints a table and writes
benchmarks/results/smoothing.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.dense_tracking import ground_truth_at  # noqa: E402
from benchmarks.machine import describe_machine  # noqa: E402
from benchmarks.sequences import camera_file_for  # noqa: E402
from tambridge.evaluation.exported import ExportedMap  # noqa: E402
from tambridge.evaluation.rendering import score_frames, score_renders  # noqa: E402
from tambridge.evaluation.trajectory import evaluate_trajectory  # noqa: E402
from tambridge.files import atomic_write_text  # noqa: E402
from tambridge.frontend.contract import FrontendResult  # noqa: E402
from tambridge.frontend.smoothing import SmoothingConfig, median_depth_m, smoothed_result  # noqa: E402
from tambridge.geometry import rotation_onto  # noqa: E402
from tambridge.io.tum import open_sequence  # noqa: E402
from tambridge.threads import TORCH_THREADS, compute_threads  # noqa: E402
from tambridge.trajectory import Trajectory, read_tum_trajectory  # noqa: E402

RESULT = ROOT / "benchmarks" / "results" / "smoothing.json"
EVERY = 5


def reconstructed(sequence: Path) -> Path:
    """The folder of a default-preset run of ``sequence`` with smoothing off (and mesh off), made in a child
    process."""
    out = ROOT / "benchmarks" / "results" / "runs" / f"smoothing__{sequence.name}"
    camera = camera_file_for(sequence)
    command = [sys.executable, str(ROOT / "cli.py"), "reconstruct", str(sequence), "-o", str(out), "--quiet",
               "--overwrite", "--set", "mesh.enabled=false", "--set", "frontend.smoothing.enabled=false",
               *(["--camera", str(camera)] if camera is not None else [])]
    out.parent.mkdir(parents=True, exist_ok=True)
    subprocess.run(command, check=True)
    return out


def scores(sequence_dir: Path, run_dir: Path) -> list[dict]:
    """Rows for the tracked trajectory of one run, the same smoothed (whole, and along the image's ambiguity) and the
    ground truth: errors against the ground truth (the last row's are about 0 by construction) and renders of its
    map. The run must have every frame of ``sequence_dir`` (no stride, no frame cap)."""
    camera = camera_file_for(sequence_dir)
    sequence = open_sequence(sequence_dir, camera_file=camera)
    tracked = read_tum_trajectory(run_dir / "trajectory.txt")
    keyframes = read_tum_trajectory(run_dir / "keyframes.txt")
    fixed = np.isin(tracked.timestamps_s, keyframes.timestamps_s)
    if len(tracked) != len(sequence):
        raise SystemExit(f"error: {run_dir / 'trajectory.txt'}: {len(tracked)} poses for {len(sequence)} frames of "
                         f"{sequence_dir}; give a run of every frame (no --set input.stride or input.max_frames)")
    run_config = _run_config(run_dir)
    if run_config.frontend.smoothing.enabled:
        raise SystemExit(f"error: {run_dir}: its trajectory.txt is smoothed already (config.yaml: "
                         "frontend.smoothing.enabled: true); give a run made with "
                         "--set frontend.smoothing.enabled=false")
    metrics = json.loads((run_dir / "metrics.json").read_text())
    if metrics["frames_lost"]:
        # reconstruct splits the smoothing at lost frames; the run folder counts them but does not say which.
        raise SystemExit(f"error: {run_dir}: {metrics['frames_lost']} frames lost, and the run folder does not say "
                         "which; this benchmark smooths only runs that lost none (compare whole runs with and without "
                         "--set frontend.smoothing.enabled=false instead)")
    # The smoothed rows as reconstruct writes them, with along_image_ambiguity off and on.
    result = FrontendResult(tracked, np.ones(len(tracked), bool), keyframes, {}, {}, np.zeros((0, 3)),
                            np.zeros((0, 3), np.uint8), np.zeros(0, np.int64), {}, 0, 0, 0)
    scene_depths_m = np.array([median_depth_m(sequence.frame_depth_m(row)) for row in range(len(sequence))])
    smoothed, along = (smoothed_result(result, SmoothingConfig(enabled=True, along_image_ambiguity=keep_along),
                                       scene_depths_m).trajectory for keep_along in (False, True))
    truth = ground_truth_in_run(sequence.ground_truth, tracked)
    frames = [index for index in range(0, len(sequence), EVERY)
              if not fixed[index] and tracked.timestamps_s[index] in truth.timestamps_s]
    exported = ExportedMap.from_run(run_dir, mapper=run_config.mapper)
    rows = []
    for name, trajectory in (("tracked", tracked), ("smoothed", smoothed),
                             ("smoothed along the image ambiguity", along), ("ground truth", truth)):
        errors = evaluate_trajectory(trajectory, sequence.ground_truth, align="se3")
        at_poses = dataclasses.replace(exported, world_from_camera=_at_frames(trajectory, tracked))
        with compute_threads(TORCH_THREADS, 0):
            rendered = score_renders(score_frames(
                sequence, lambda index: at_poses.render(sequence.camera, index).rgb, frames))
        summary = rendered.summary()
        rows.append({"sequence": sequence_dir.name, "trajectory": name, "frames": len(tracked),
                     "keyframes": int(fixed.sum()),
                     "rendered_frames": len(frames),
                     "ate_cm": 100 * errors.ate_rmse_m, "max_cm": 100 * errors.ate_max_m,
                     "rpe_cm": 100 * errors.rpe_trans_rmse_m, "rpe_deg": errors.rpe_rot_rmse_deg,
                     "psnr_db": summary["psnr_db"], "ssim": summary["ssim"]})
    return rows


def ground_truth_in_run(ground_truth: Trajectory, tracked: Trajectory) -> Trajectory:
    """The ground truth interpolated at ``tracked``'s frame times inside its span, moved into the run's world by the
    rigid transform that best maps its poses onto the tracked ones, orientations included: the rotation is the
    chordal mean of ``R_tracked R_truth^T``, then the translation the mean of the positions' differences. (Umeyama's
    fit of the positions alone leaves the rotation about a nearly straight path loose, which a render shows.)"""
    truth = ground_truth_at(ground_truth, tracked.timestamps_s)
    tracked_at = tracked.world_from_camera[np.searchsorted(tracked.timestamps_s, truth.timestamps_s)]
    run_from_truth = np.eye(4)
    run_from_truth[:3, :3] = rotation_onto(tracked_at[:, :3, :3], truth.world_from_camera[:, :3, :3])
    run_from_truth[:3, 3] = np.mean(tracked_at[:, :3, 3] - truth.positions_m @ run_from_truth[:3, :3].T, axis=0)
    return Trajectory(truth.timestamps_s, run_from_truth @ truth.world_from_camera)


def _at_frames(trajectory: Trajectory, tracked: Trajectory) -> np.ndarray:
    """(N, 4, 4) world_from_camera, one per frame of ``tracked``: ``trajectory``'s pose where it has the frame's time,
    the tracked pose elsewhere (frames that are not rendered)."""
    world_from_camera = tracked.world_from_camera.copy()
    rows = np.searchsorted(tracked.timestamps_s, trajectory.timestamps_s)
    assert np.array_equal(tracked.timestamps_s[rows], trajectory.timestamps_s)
    world_from_camera[rows] = trajectory.world_from_camera
    return world_from_camera


def _run_config(run_dir: Path):
    """The settings ``run_dir``'s config.yaml recorded (the mapper's rasteriser backend renders the splats)."""
    from tambridge.config import load_config

    return load_config(run_dir / "config.yaml", [])


def table(rows: list[dict]) -> str:
    lines = ["| sequence | trajectory | ATE cm | largest cm | RPE cm / deg per frame | splats.ply at it: PSNR dB / "
             "SSIM (frames) |", "|---|---|---|---|---|---|"]
    for row in rows:
        lines.append(f"| {row['sequence']} | {row['trajectory']} | {row['ate_cm']:.3f} | {row['max_cm']:.2f} | "
                     f"{row['rpe_cm']:.3f} / {row['rpe_deg']:.3f} | {row['psnr_db']:.2f} / {row['ssim']:.3f} "
                     f"({row['rendered_frames']}) |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sequences", nargs="+", type=Path, help="TUM-layout folders with groundtruth.txt")
    parser.add_argument("--output", type=Path, default=RESULT)
    args = parser.parse_args()
    rows = [row for sequence in args.sequences for row in scores(sequence, reconstructed(sequence))]
    print(table(rows))
    document = {"date": datetime.date.today().isoformat(), "machine": describe_machine(),
                "command": " ".join(sys.argv), "rows": rows}
    atomic_write_text(args.output, json.dumps(document, indent=2) + "\n")


if __name__ == "__main__":
    main()
