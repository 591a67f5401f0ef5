"""Where tracking's pose errors come from on TUM sequences, whose depth image is taken up to 20 ms from its colour
image: per-frame error against the colour stamp's offset from the depth stamp times the camera's velocity.

    python benchmarks/depth_stamps.py                                      # fr1/xyz, default settings
    python benchmarks/depth_stamps.py --variants "" depth_time_compensation=true --segments fr1_xyz fr1_xyz_first37
    python benchmarks/depth_stamps.py --segments --folder SYNTH_DIR      # a synthetic sequence (tambridge synth)

Each variant is one tracking run (the ORB frontend, default settings plus the variant's ``KEY=VALUE`` overrides
separated by commas, "" for none; loop closure, global BA, mapping thread) over a segment of
``benchmarks/dense_tracking.py``. The ground truth is interpolated at the colour stamps. Per frame: the aligned
position error ``e`` (SE(3) alignment), the camera's displacement between its depth and colour image ``d = v (t_depth
- t_colour)`` (``v`` the ground truth's velocity), the inlier count. The table lists the worst frames; the summary
gives how much of the error ``d`` explains: the least-squares fit ``e ~ a d`` (a = 1 when the pose sits at the depth's
time; explained share ``1 - |e - a d|^2 / |e|^2``), the same for the frame-to-frame changes of ``e`` and ``d`` (the
jitter), the correlation of ``|e|`` with ``|d|``, the speed and the inlier count, and how much of ``e`` (in the camera
frame) a linear function of the camera's velocity (and angular velocity) explains: its diagonal, in ms, is the lag of
each axis (``e_x ~ lag v_x``), and each worst frame gets the error that fit leaves. frames/s is wall time inside
``track``/``finish``; CPU frames/s uses the process CPU time (all threads) over the same calls. Rows go to
benchmarks/results/depth_stamps.json.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.dense_tracking import SEGMENTS, ground_truth_at, orb_config  # noqa: E402
from benchmarks.machine import describe_machine  # noqa: E402
from tambridge.files import atomic_write_text  # noqa: E402

WORST_FRAMES = 12


def share_explained(errors: np.ndarray, displacements: np.ndarray) -> tuple[float, float]:
    """``(a, explained share)`` of the fit ``errors ~ a displacements`` over (N, 3) vectors."""
    scale = float(np.sum(errors * displacements) / max(np.sum(displacements * displacements), 1e-300))
    residual = errors - scale * displacements
    return scale, float(1.0 - np.sum(residual**2) / max(np.sum(errors**2), 1e-300))


def linear_fit(errors: np.ndarray, regressors: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """``(B (R, 3), explained share, residual (N, 3))`` of the least-squares fit ``errors (N, 3) ~ regressors (N, R)
    @ B + c``."""
    design = np.column_stack([regressors, np.ones(len(regressors))])
    solution = np.linalg.lstsq(design, errors, rcond=None)[0]
    residual = errors - design @ solution
    centred = errors - errors.mean(axis=0)
    return solution[:-1], float(1.0 - np.sum(residual**2) / max(np.sum(centred**2), 1e-300)), residual


def track(frames, sequence, config) -> dict:
    """One tracking run with the ORB frontend's ``config``: per-frame records and the run's figures."""
    from tambridge.evaluation.trajectory import evaluate_trajectory
    from tambridge.frontend.orb.frontend import OrbFrontend

    frontend = OrbFrontend(sequence.camera, config)
    inliers = {}
    wall_s = cpu_s = 0.0
    load = os.getloadavg()[0]
    for frame in frames:
        started, cpu_started = time.perf_counter(), time.process_time()
        result = frontend.track(frame)
        wall_s += time.perf_counter() - started
        cpu_s += time.process_time() - cpu_started
        inliers[frame.timestamp_s] = result.inlier_count
    started, cpu_started = time.perf_counter(), time.process_time()
    estimate = frontend.finish().trajectory
    wall_s += time.perf_counter() - started
    cpu_s += time.process_time() - cpu_started
    truth = ground_truth_at(sequence.ground_truth, estimate.timestamps_s)
    errors = evaluate_trajectory(estimate, truth, align="se3", max_time_difference_s=1e-6)
    return {"errors": errors, "inliers": inliers, "wall_s": wall_s, "cpu_s": cpu_s, "load_1min": load}


def analyse(frames, sequence, run: dict) -> dict:
    """The per-frame table and the summary of one run (see the module docstring)."""
    errors = run["errors"]
    times = errors.timestamps_s
    by_time = {frame.timestamp_s: frame for frame in frames}
    delay_s = np.array([by_time[t].depth_delay_s for t in times])
    step_s = 0.005
    before = ground_truth_at(sequence.ground_truth, times - step_s)
    after = ground_truth_at(sequence.ground_truth, times + step_s)
    keep = np.isin(times - step_s, before.timestamps_s) & np.isin(times + step_s, after.timestamps_s)
    velocity = np.zeros((len(times), 3))
    velocity[keep] = (after.world_from_camera[np.isin(after.timestamps_s, times[keep] + step_s), :3, 3]
                      - before.world_from_camera[np.isin(before.timestamps_s, times[keep] - step_s), :3, 3]) / (2 * step_s)
    displacement = velocity * delay_s[:, None]
    truth_rotation = errors.ref.world_from_camera[:, :3, :3]
    velocity_camera = np.einsum("nji,nj->ni", truth_rotation, velocity)
    angular_velocity = np.zeros((len(times), 3))
    turn = np.einsum("nji,njk->nik", before.world_from_camera[np.isin(before.timestamps_s, times[keep] - step_s), :3, :3],
                     after.world_from_camera[np.isin(after.timestamps_s, times[keep] + step_s), :3, :3])
    angular_velocity[keep] = Rotation.from_matrix(turn).as_rotvec() / (2 * step_s)
    error = errors.aligned_est.world_from_camera[:, :3, 3] - errors.ref.world_from_camera[:, :3, 3]
    error = error - error.mean(axis=0)
    error_camera = np.einsum("nji,nj->ni", truth_rotation, error)
    velocity_fit = linear_fit(error_camera, velocity_camera)
    motion_fit = linear_fit(error_camera, np.column_stack([velocity_camera, angular_velocity]))
    inliers = np.array([run["inliers"][t] for t in times], float)
    norm_e, norm_d = np.linalg.norm(error, axis=1), np.linalg.norm(displacement, axis=1)
    scale, explained = share_explained(error, displacement)
    jitter_scale, jitter_explained = share_explained(np.diff(error, axis=0), np.diff(displacement, axis=0))
    worst = np.argsort(-norm_e)[:WORST_FRAMES]
    table = [{"frame": int(by_time[times[i]].index), "t_s": float(times[i] - times[0]), "error_cm": 100 * float(norm_e[i]),
              "depth_minus_colour_ms": 1e3 * float(delay_s[i]), "speed_m_s": float(np.linalg.norm(velocity[i])),
              "displacement_mm": 1e3 * float(norm_d[i]),
              "error_along_displacement_mm": 1e3 * float(error[i] @ displacement[i] / max(norm_d[i], 1e-12)),
              "inliers": int(inliers[i]), "left_after_motion_fit_cm": 100 * float(np.linalg.norm(motion_fit[2][i]))}
             for i in worst]
    return {
        "ate_cm": 100 * errors.ate_rmse_m, "max_cm": 100 * errors.ate_max_m, "rpe_cm": 100 * errors.rpe_trans_rmse_m,
        "poses": errors.pose_count, "fps": len(frames) / run["wall_s"], "cpu_fps": len(frames) / run["cpu_s"],
        "load_1min": run["load_1min"],
        "fit_error_on_displacement": {"a": scale, "explained": explained},
        "fit_jitter_on_displacement_change": {"a": jitter_scale, "explained": jitter_explained},
        "fit_error_camera_on_velocity_camera": {"lag_ms_per_axis": [1e3 * float(velocity_fit[0][i, i]) for i in range(3)],
                                                 "explained": velocity_fit[1]},
        "fit_error_camera_on_velocity_and_angular_velocity": {"explained": motion_fit[1]},
        "corr_error_displacement": float(np.corrcoef(norm_e, norm_d)[0, 1]),
        "corr_error_inliers": float(np.corrcoef(norm_e, inliers)[0, 1]),
        "corr_error_speed": float(np.corrcoef(norm_e, np.linalg.norm(velocity, axis=1))[0, 1]),
        "displacement_mm_median_max": [1e3 * float(np.median(norm_d)), 1e3 * float(norm_d.max())],
        "worst_frames": table,
    }


def main() -> None:
    from tambridge.io.tum import open_sequence

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--segments", nargs="*", default=["fr1_xyz"], choices=list(SEGMENTS))
    parser.add_argument("--folder", type=Path, action="append", default=[],
                        help="also a whole sequence folder (a synthetic one: tambridge synth)")
    parser.add_argument("--variants", nargs="*", default=[""], help="comma-separated KEY=VALUE overrides per run")
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks" / "results" / "depth_stamps.json")
    args = parser.parse_args()
    configs = {variant: orb_config(list(filter(None, variant.split(",")))) for variant in args.variants}
    rows = []
    segments = {name: SEGMENTS[name] for name in args.segments}
    segments.update({folder.name: dict(folder=folder, camera=None, start=0, end=None) for folder in args.folder})
    for name, segment in segments.items():
        sequence = open_sequence(segment["folder"], camera_file=segment["camera"])
        end = len(sequence) if segment["end"] is None else min(segment["end"], len(sequence))
        frames = [sequence[index] for index in range(segment["start"], end)]
        for variant in args.variants:
            row = {"segment": name, "variant": variant or "default",
                   **analyse(frames, sequence, track(frames, sequence, configs[variant]))}
            rows.append(row)
            print(f"{name} [{row['variant']}]: ATE {row['ate_cm']:.3f} cm, max {row['max_cm']:.2f} cm, RPE "
                  f"{row['rpe_cm']:.3f} cm/frame, {row['fps']:.1f} frames/s wall, {row['cpu_fps']:.1f} CPU (load "
                  f"{row['load_1min']:.1f}); e ~ a d: a {row['fit_error_on_displacement']['a']:.2f}, explained "
                  f"{row['fit_error_on_displacement']['explained']:.3f}; jitter a "
                  f"{row['fit_jitter_on_displacement_change']['a']:.2f}, explained "
                  f"{row['fit_jitter_on_displacement_change']['explained']:.3f}; corr |e| with |d| "
                  f"{row['corr_error_displacement']:.2f}, with inliers {row['corr_error_inliers']:.2f}, with speed "
                  f"{row['corr_error_speed']:.2f}; camera-frame e ~ B v: diagonal "
                  f"{', '.join(f'{lag:.1f}' for lag in row['fit_error_camera_on_velocity_camera']['lag_ms_per_axis'])} ms, "
                  f"explained {row['fit_error_camera_on_velocity_camera']['explained']:.2f} (with angular velocity "
                  f"{row['fit_error_camera_on_velocity_and_angular_velocity']['explained']:.2f})", flush=True)
            print("  frame   t s  error cm  depth-colour ms  speed m/s  |d| mm  e along d mm  inliers  left after fit cm")
            for entry in row["worst_frames"]:
                print(f"  {entry['frame']:5d} {entry['t_s']:5.2f} {entry['error_cm']:9.2f} {entry['depth_minus_colour_ms']:16.1f} "
                      f"{entry['speed_m_s']:10.2f} {entry['displacement_mm']:7.2f} {entry['error_along_displacement_mm']:13.2f} "
                      f"{entry['inliers']:8d} {entry['left_after_motion_fit_cm']:17.2f}", flush=True)
    atomic_write_text(args.output, json.dumps({"machine": describe_machine(), "rows": rows},
                                              indent=2) + "\n")


if __name__ == "__main__":
    main()
