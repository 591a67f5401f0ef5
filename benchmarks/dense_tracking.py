"""The dense point-to-plane depth term of ORB tracking (``dense_depth`` never / auto / always) on real and synthetic
segments: ATE, RPE, the largest error, tracking frames/s, and the term's own cost per frame.

    python benchmarks/dense_tracking.py                                   # every segment below
    python benchmarks/dense_tracking.py --segments fr1_xyz_0-300 --modes never auto
    python benchmarks/dense_tracking.py --segments fr1_xyz 7scenes_450-550 --modes always --strides 1 2 4

``--strides``: each segment also with every n-th frame only, the camera n times as fast (real motion, real
images, no added blur): a real-data stand-in for fast rotation, and a run through the lost-frame and
relocalisation paths where tracking breaks. ``--exposure-frames N`` (odd) adds the blur of a longer exposure: each
tracked frame's colour is the mean of the N recorded frames centred on it (blurred along the camera's real
motion, N/30 s at 30 frames/s), its depth and stamps its own. ``--offsets K ...`` starts each strided run at the
segment's K-th frame as well: the same motion through other frames, which at large strides decides which frames
are lost. ``--lost-priors`` asks, at each frame a run loses, whether the image or the prior was at fault
(:func:`lost_frame_priors`).

Tracking only (the ORB frontend with the default settings: loop closure, global BA, mapping thread), no
Gaussian mapping. frames/s counts the time inside ``track`` and ``finish``; under shared CPUs compare the modes'
ratio within one run, not absolute figures. ATE is the RMSE after SE(3) alignment over the segment; ``max cm``
is the largest aligned error; RPE the translational RMSE between consecutive frames. The "smoothed" columns score
the trajectory a default run writes (`frontend.smoothing`): the same one smoothed about its keyframes
(tambridge/frontend/smoothing.py). ``tracking CPU ms/frame`` is
the CPU time of the tracking thread inside ``track`` (thread time: the mapping thread and other processes do not
count), the figure to hold against 33 ms for 30 frames/s. The term's cost is also timed
apart on the segment's frames: sampling the frame's depth, one evaluation of the kernel (a Gauss-Newton step
evaluates it once), and building a keyframe's vertex and normal maps. Rows go to
benchmarks/results/dense_tracking.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import describe_machine  # noqa: E402
from benchmarks.sped_up_sequence import mean_exposure  # noqa: E402
from tambridge.files import atomic_write_text  # noqa: E402

SHARED = ROOT.parent / "shared" / "data"
KITCHEN = dict(folder=SHARED / "7scenes_redkitchen_0-699", camera=ROOT / "configs" / "cameras" / "7scenes_kinect.yaml")
# name -> folder, camera file (None: the folder's own), first frame, end frame (None: the last).
SEGMENTS = {
    "fr1_xyz_0-300": dict(folder=ROOT.parent / "data" / "rgbd_dataset_freiburg1_xyz", camera=None, start=0, end=300),
    "fr1_xyz": dict(folder=ROOT.parent / "data" / "rgbd_dataset_freiburg1_xyz", camera=None, start=0, end=None),
    "fr1_xyz_first37": dict(folder=SHARED / "tum_fr1_xyz_first37", camera=None, start=0, end=None),
    "7scenes_100-150": dict(**KITCHEN, start=100, end=150),
    "7scenes_450-550": dict(**KITCHEN, start=450, end=550),
    "7scenes_0-699": dict(**KITCHEN, start=0, end=None),
}
MODES = ("never", "auto", "always")


def orb_config(overrides: list[str]):
    """The ORB frontend's settings with ``KEY=VALUE`` overrides of ``frontend.orb``, parsed and checked as the CLI's
    ``--set`` is (:func:`tambridge.config.load_config`): an unknown key or a bad value exits with its one-line error."""
    from tambridge.config import load_config
    from tambridge.errors import ConfigError

    try:
        return load_config(None, [f"frontend.orb.{item}" for item in overrides]).frontend.orb
    except ConfigError as error:
        raise SystemExit(f"error: {error}") from None


def track_segment(frames, sequence, config, trajectory_path: Path | None = None):
    """``(trajectory, row)`` of one tracking run over ``frames`` with the ORB frontend's ``config``."""
    from tambridge.evaluation.trajectory import evaluate_trajectory
    from tambridge.frontend.orb.frontend import OrbFrontend
    from tambridge.frontend.smoothing import SmoothingConfig, median_depth_m, smoothed_result

    frontend = OrbFrontend(sequence.camera, config)
    started = time.perf_counter()
    thread_cpu_s = 0.0
    scene_depths_m, depth_medians_s = [], 0.0
    for frame in frames:
        cpu_started = time.thread_time()
        frontend.track(frame)
        thread_cpu_s += time.thread_time() - cpu_started
        medians_started = time.perf_counter()
        scene_depths_m.append(median_depth_m(frame.depth_m))
        depth_medians_s += time.perf_counter() - medians_started
    result = frontend.finish()
    tracking_s = time.perf_counter() - started - depth_medians_s  # the smoothing's depths are not tracking's time
    errors = evaluate_trajectory(result.trajectory, sequence.ground_truth, align="se3")
    # What a default `tambridge reconstruct` writes: smoothed about the keyframes.
    smoothed_run = smoothed_result(result, SmoothingConfig(enabled=True), np.array(scene_depths_m))
    smoothed = evaluate_trajectory(smoothed_run.trajectory, sequence.ground_truth, align="se3")
    if trajectory_path is not None:
        from tambridge.trajectory import write_tum_trajectory

        write_tum_trajectory(trajectory_path, result.trajectory)
    return result.trajectory, {"mode": config.dense_depth.value, "frames": len(frames), "ate_cm": 100 * errors.ate_rmse_m,
            "max_cm": 100 * errors.ate_max_m, "rpe_cm": 100 * errors.rpe_trans_rmse_m,
            "rpe_deg": errors.rpe_rot_rmse_deg, "smoothed_ate_cm": 100 * smoothed.ate_rmse_m,
            "smoothed_max_cm": 100 * smoothed.ate_max_m, "smoothed_rpe_cm": 100 * smoothed.rpe_trans_rmse_m,
            "fps": len(frames) / tracking_s, "tracking_s": tracking_s,
            "tracking_thread_cpu_ms": 1e3 * thread_cpu_s / len(frames), "stage_s": result.timings_s,
            "frames_with_dense": frontend.frames_with_dense_depth, "lost": result.frames_lost,
            "tracked_by_depth": result.frames_tracked_by_depth,
            "keyframes": len(result.keyframe_poses), "loops": result.loops_closed}


def term_cost(frames, sequence) -> dict:
    """Milliseconds of the term's parts, medians over the segment's frames against the first frame's depth."""
    from tambridge.frontend.orb.config import OrbFrontendConfig, scaled_for_image
    from tambridge.frontend.orb.dense_depth import (
        DenseTerm,
        dense_normal_equations,
        dense_reference,
        dense_samples,
    )

    config = scaled_for_image(OrbFrontendConfig(), sequence.camera.width, sequence.camera.height)
    K = sequence.camera.K
    pose = np.linalg.inv(sequence.ground_truth.world_from_camera[0]) if len(sequence.ground_truth) else np.eye(4)
    sample_ms, kernel_ms, reference_ms, counts = [], [], [], []
    for frame in frames[: min(len(frames), 30)]:
        started = time.perf_counter()
        reference = dense_reference(0, frame.depth_m, K, config.dense_reference_stride_px, config.min_depth_m, config.max_depth_m)
        reference_ms.append(1e3 * (time.perf_counter() - started))
        started = time.perf_counter()
        samples = dense_samples(frame.depth_m, K, config.dense_sample_stride_px, config.min_depth_m, config.max_depth_m)
        sample_ms.append(1e3 * (time.perf_counter() - started))
        term = DenseTerm(reference, pose, samples, K, config.dense_depth_weight, config.dense_depth_noise_per_m,
                         config.dense_depth_huber_sigmas, config.dense_depth_max_distance_m)
        dense_normal_equations(pose, term)  # compiled before it is timed
        started = time.perf_counter()
        dense_normal_equations(pose, term)
        kernel_ms.append(1e3 * (time.perf_counter() - started))
        counts.append(len(samples))
    return {"samples_per_frame": int(np.median(counts)), "sampling_ms": float(np.median(sample_ms)),
            "kernel_ms_per_step": float(np.median(kernel_ms)), "keyframe_maps_ms": float(np.median(reference_ms))}


def ground_truth_at(ground_truth, timestamps_s: np.ndarray):
    """The ground truth interpolated at ``timestamps_s`` (those inside its span): a Trajectory."""
    from tambridge.geometry import interpolate_pose
    from tambridge.trajectory import Trajectory

    times = ground_truth.timestamps_s
    inside = (timestamps_s > times[0]) & (timestamps_s < times[-1])
    after = np.searchsorted(times, timestamps_s[inside])
    poses = [interpolate_pose(ground_truth.world_from_camera[a - 1], ground_truth.world_from_camera[a],
                              (t - times[a - 1]) / (times[a] - times[a - 1])) for t, a in zip(timestamps_s[inside], after)]
    return Trajectory(timestamps_s[inside], np.stack(poses))


def time_offset_scan(estimate, ground_truth, offsets_ms=range(-100, 110, 10)) -> dict:
    """ATE (cm) of ``estimate`` against the ground truth interpolated at the frame times shifted by each offset:
    a minimum away from 0 is a clock offset between the camera and the motion capture."""
    from tambridge.evaluation.trajectory import evaluate_trajectory
    from tambridge.trajectory import Trajectory

    scan = {}
    for offset_ms in offsets_ms:
        reference = ground_truth_at(ground_truth, estimate.timestamps_s + offset_ms / 1e3)
        shifted = Trajectory(reference.timestamps_s - offset_ms / 1e3, reference.world_from_camera)
        scan[int(offset_ms)] = 100 * evaluate_trajectory(estimate, shifted, align="se3", max_time_difference_s=1e-6).ate_rmse_m
    return scan


def lost_frame_priors(frames, sequence, config, radius_scales=(4.0, 6.0)) -> dict:
    """Whether a lost frame is lost for its image or for its prior. Tracks ``frames`` inline and, right after each
    frame tracking loses, repeats its first local-map search (the same features, keypoint grid and depth, the radius
    doubled as after a loss) from two other priors: the ground-truth pose, put into the run's world through the first
    tracked frame, and the frontend's own prior with that radius times each of ``radius_scales``. Per lost frame: its
    position in ``frames``, how the frame before it was placed, its prior's distance from the ground truth (cm,
    degrees), for each search the inliers and the distance of the pose found (cm), and its error in the run's final
    trajectory (SE(3)-aligned, cm; bridged by the frames around it); with the count of the run's frames over 5 cm,
    and how many of them are lost."""
    from tambridge.evaluation.trajectory import evaluate_trajectory
    from tambridge.frontend.orb.frontend import OrbFrontend
    from tambridge.geometry import inverse, rotation_angle_deg

    frontend = OrbFrontend(sequence.camera, dataclasses.replace(config, mapping_thread=False))
    truth = ground_truth_at(sequence.ground_truth, np.array([frame.timestamp_s for frame in frames]))
    truth_by_time = dict(zip(truth.timestamps_s, truth.world_from_camera))
    track_local_map, searches = frontend._track_local_map, []

    def recorded(features, grid, predicted, radius_scale, depth_m):
        searches.append((features, grid, predicted, depth_m))
        return track_local_map(features, grid, predicted, radius_scale, depth_m)

    frontend._track_local_map = recorded

    def searched(camera_from_world, radius_scale, truth_pose) -> dict:
        features, grid, _, depth_m = searches[0]
        fix, _, _ = track_local_map(features, grid, camera_from_world, radius_scale, depth_m)
        if fix is None:
            return {"inliers": 0, "error_cm": None}
        error_m = np.linalg.norm(inverse(fix.camera_from_world)[:3, 3] - truth_pose[:3, 3])
        return {"inliers": int(fix.inlier_count), "error_cm": round(100 * float(error_m), 2)}

    run_world_from_truth_world, rows, before = None, [], "none"
    for position, frame in enumerate(frames):
        searches.clear()
        lost_before = frontend.frames_lost
        result = frontend.track(frame)
        if run_world_from_truth_world is None and result.tracked and frame.timestamp_s in truth_by_time:
            run_world_from_truth_world = result.world_from_camera @ inverse(truth_by_time[frame.timestamp_s])
        # A frame that starts a map segment is not lost: the new segment's map is its own.
        lost = frontend.frames_lost > lost_before
        if lost and searches and run_world_from_truth_world is not None and frame.timestamp_s in truth_by_time:
            truth_pose = run_world_from_truth_world @ truth_by_time[frame.timestamp_s]
            prior = searches[0][2]
            row = {"position": position, "after": before,
                   "prior_error_cm": round(100 * float(np.linalg.norm(inverse(prior)[:3, 3] - truth_pose[:3, 3])), 2),
                   "prior_error_deg": round(rotation_angle_deg(prior @ truth_pose), 2),
                   "from_ground_truth": searched(inverse(truth_pose), 2.0, truth_pose)}
            for scale in radius_scales:
                row[f"from_prior_radius_x{scale:g}"] = searched(prior, 2.0 * scale, truth_pose)
            rows.append(row)
        before = "lost" if lost else "relocalised" if result.relocalised else "tracked" if result.tracked else "segment start"
    final = frontend.finish()
    errors = evaluate_trajectory(final.trajectory, sequence.ground_truth, align="se3")
    error_by_time = dict(zip(errors.timestamps_s, errors.ate_errors_m))
    for row in rows:
        row["final_error_cm"] = round(100 * float(error_by_time[frames[row["position"]].timestamp_s]), 2)
    over = {position for position, frame in enumerate(frames) if error_by_time.get(frame.timestamp_s, 0.0) > 0.05}
    return {"lost": rows, "frames_over_5cm": len(over),
            "lost_frames_over_5cm": len(over.intersection(row["position"] for row in rows))}


def lost_priors_summary(diagnosis: dict, min_inliers: int) -> str:
    """One line: the lost frames, their priors' median distance from the truth, and per search how many it places
    (``min_inliers``), how many of those within 5 cm and the worst; then the run's frames over 5 cm."""
    rows = diagnosis["lost"]
    if not rows:
        return f"no lost frames; {diagnosis['frames_over_5cm']} frames over 5 cm in the run"
    parts = [f"{len(rows)} lost frames; their priors {np.median([row['prior_error_cm'] for row in rows]):.1f} cm off "
             "(median)"]
    for search in [key for key in rows[0] if key.startswith("from_")]:
        placed = [row[search]["error_cm"] for row in rows if row[search]["inliers"] >= min_inliers]
        parts.append(f"{search}: {len(placed)} placed, {sum(error <= 5.0 for error in placed)} within 5 cm, worst "
                     f"{max(placed, default=0.0):.2f} cm")
    parts.append(f"{diagnosis['frames_over_5cm']} frames over 5 cm in the run, {diagnosis['lost_frames_over_5cm']} of "
                 "them lost")
    return "; ".join(parts)


def depth_fit(frames, sequence, estimate, gap: int = 1, step: int = 10) -> dict:
    """How well relative poses fit the depth: for frame pairs (i, i + gap), the median absolute point-to-plane
    residual (mm) of frame i + gap's depth against frame i's at the ground truth's relative pose, at the
    estimate's, and at the depth's own optimum (Gauss-Newton on the dense term alone from the ground truth); and
    the translation (mm) between the ground truth's relative pose and that optimum, whose RMS is the floor of an
    RPE that fits the depth best."""
    from tambridge.frontend.orb.config import OrbFrontendConfig, scaled_for_image
    from tambridge.frontend.orb.dense_depth import (
        DenseTerm,
        dense_normal_equations,
        dense_reference,
        dense_residuals_reference,
        dense_samples,
    )
    from tambridge.geometry import exp_se3, inverse

    config = scaled_for_image(OrbFrontendConfig(), sequence.camera.width, sequence.camera.height)
    K = sequence.camera.K
    # The depth was taken at its own stamp, not the colour's.
    times = np.array([frame.timestamp_s + frame.depth_delay_s for frame in frames])
    truth = ground_truth_at(sequence.ground_truth, times)
    truth_by_time = dict(zip(truth.timestamps_s, truth.world_from_camera))
    estimate_by_time = dict(zip(estimate.timestamps_s, estimate.world_from_camera))
    at_truth, at_estimate, at_optimum, truth_gap = [], [], [], []
    for i in range(0, len(frames) - gap, step):
        a, b = frames[i], frames[i + gap]
        if times[i] not in truth_by_time or times[i + gap] not in truth_by_time:
            continue
        reference = dense_reference(0, a.depth_m, K, config.dense_reference_stride_px, config.min_depth_m, config.max_depth_m)
        samples = dense_samples(b.depth_m, K, config.dense_sample_stride_px // 2, config.min_depth_m, config.max_depth_m)
        term = DenseTerm(reference, np.eye(4), samples, K, 1.0, config.dense_depth_noise_per_m,
                         config.dense_depth_huber_sigmas, config.dense_depth_max_distance_m)

        def median_mm(b_from_a, term=term):
            residual, _, associated = dense_residuals_reference(b_from_a, term)[:3]
            return 1e3 * float(np.median(np.abs(residual[associated])))

        truth_pose = inverse(truth_by_time[times[i + gap]]) @ truth_by_time[times[i]]
        optimum = truth_pose
        for _ in range(20):
            hessian, gradient, _, _ = dense_normal_equations(optimum, term)
            delta = -np.linalg.solve(hessian + 1e-12 * np.eye(6), gradient)
            optimum = exp_se3(delta) @ optimum
            if np.linalg.norm(delta) < 1e-7:
                break
        at_truth.append(median_mm(truth_pose))
        at_optimum.append(median_mm(optimum))
        truth_gap.append(1e3 * np.linalg.norm((optimum @ inverse(truth_pose))[:3, 3]))
        if a.timestamp_s in estimate_by_time and b.timestamp_s in estimate_by_time:
            at_estimate.append(median_mm(inverse(estimate_by_time[b.timestamp_s]) @ estimate_by_time[a.timestamp_s]))
    return {"pairs": len(at_truth), "gap_frames": gap, "residual_mm_at_ground_truth": float(np.median(at_truth)),
            "residual_mm_at_estimate": float(np.median(at_estimate)) if at_estimate else None,
            "residual_mm_at_depth_optimum": float(np.median(at_optimum)),
            "ground_truth_to_depth_optimum_rms_mm": float(np.sqrt(np.mean(np.square(truth_gap))))}


def longer_exposure(frames: list, index: int, count: int):
    """Frame ``index`` of ``frames`` with its colour the mean of the ``count`` (odd) consecutive frames centred on it
    (fewer at the ends): a longer exposure, blurred along the camera's real motion; its depth and stamps its own."""
    if count == 1:
        return frames[index]
    half = count // 2
    window = frames[max(0, index - half) : index + half + 1]
    return dataclasses.replace(frames[index], rgb=mean_exposure([frame.rgb for frame in window]))


def format_table(rows: list[dict]) -> str:
    columns = [("segment", "segment", "{}"), ("stride", "stride", "{}"), ("offset", "offset", "{}"),
               ("exposure frames", "exposure_frames", "{}"),
               ("dense_depth", "mode", "{}"), ("frames", "frames", "{}"),
               ("ATE cm", "ate_cm", "{:.2f}"), ("max cm", "max_cm", "{:.2f}"), ("RPE cm/frame", "rpe_cm", "{:.3f}"),
               ("RPE deg/frame", "rpe_deg", "{:.3f}"), ("smoothed: ATE cm", "smoothed_ate_cm", "{:.2f}"),
               ("max cm", "smoothed_max_cm", "{:.2f}"), ("RPE cm/frame", "smoothed_rpe_cm", "{:.3f}"),
               ("frames/s", "fps", "{:.1f}"),
               ("tracking CPU ms/frame", "tracking_thread_cpu_ms", "{:.1f}"),
               ("frames with term", "frames_with_dense", "{}"), ("lost", "lost", "{}"),
               ("tracked by depth", "tracked_by_depth", "{}"), ("keyframes", "keyframes", "{}")]
    lines = ["| " + " | ".join(title for title, _, _ in columns) + " |", "|" + "---|" * len(columns)]
    for row in rows:
        lines.append("| " + " | ".join("-" if row.get(key) is None else form.format(row[key]) for _, key, form in columns) + " |")
    return "\n".join(lines)


def main() -> None:
    from tambridge.io.tum import open_sequence

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--segments", nargs="*", default=list(SEGMENTS), choices=list(SEGMENTS))
    parser.add_argument("--folder", type=Path, action="append", default=[],
                        help="also a whole sequence folder (a synthetic one: tambridge synth)")
    parser.add_argument("--modes", nargs="*", default=list(MODES), choices=MODES)
    parser.add_argument("--offsets", nargs="*", type=int, default=[0], metavar="K",
                        help="also start each strided run at the segment's K-th frame (K below the stride; others are "
                        "skipped for that stride): other frames of the same motion (default 0)")
    parser.add_argument("--strides", nargs="*", type=int, default=[1], metavar="N",
                        help="also track every N-th frame only (the camera N times as fast); default 1")
    parser.add_argument("--exposure-frames", type=int, default=1, metavar="N",
                        help="each tracked frame's colour the mean of N (odd) consecutive frames: a longer exposure")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="OrbFrontendConfig overrides")
    parser.add_argument("--trajectories", type=Path, help="write each run's trajectory here (SEGMENT_MODE.txt)")
    parser.add_argument("--limits", action="store_true", help="also scan clock offsets against the ground truth and "
                        "measure how well its relative poses fit the depth (with the last stride's and mode's trajectory)")
    parser.add_argument("--lost-priors", action="store_true", help="also track each run once more inline "
                        "and, at each lost frame, search the local map from the ground-truth pose and with a wider "
                        "radius: is a frame lost for its image or for its prior?")
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks" / "results" / "dense_tracking.json")
    args = parser.parse_args()
    if any(stride < 1 for stride in args.strides):
        parser.error(f"--strides {' '.join(map(str, args.strides))}: each must be 1 or more")
    if any(offset < 0 for offset in args.offsets):
        parser.error(f"--offsets {' '.join(map(str, args.offsets))}: each must be 0 or more")
    if args.exposure_frames < 1 or args.exposure_frames % 2 == 0:
        parser.error(f"--exposure-frames {args.exposure_frames}: give an odd count, 1 or more")
    configs = {mode: orb_config([f"dense_depth={mode}", *args.set]) for mode in args.modes}
    segments = {name: SEGMENTS[name] for name in args.segments}
    if args.trajectories is not None:
        args.trajectories.mkdir(parents=True, exist_ok=True)
    segments.update({folder.name: dict(folder=folder, camera=None, start=0, end=None) for folder in args.folder})
    rows, costs, limits = [], {}, {}
    for name, segment in segments.items():
        sequence = open_sequence(segment["folder"], camera_file=segment["camera"])
        end = len(sequence) if segment["end"] is None else min(segment["end"], len(sequence))
        frames = [sequence[index] for index in range(segment["start"], end)]
        costs[name] = term_cost(frames, sequence)
        for stride, offset in [(stride, offset) for stride in args.strides for offset in args.offsets if offset < stride]:
            for mode in args.modes:
                suffix = ("" if stride == 1 else f"_stride{stride}") + ("" if offset == 0 else f"_offset{offset}") + \
                    ("" if args.exposure_frames == 1 else f"_exposure{args.exposure_frames}")
                path = None if args.trajectories is None else args.trajectories / f"{name}_{mode}{suffix}.txt"
                used = [longer_exposure(frames, index, args.exposure_frames) for index in range(offset, len(frames), stride)]
                trajectory, row = track_segment(used, sequence, configs[mode], path)
                row = {"segment": name, "stride": stride, "offset": offset, "exposure_frames": args.exposure_frames,
                       **row, "load_1min": os.getloadavg()[0]}
                print(format_table([row]).splitlines()[-1], flush=True)
                if args.lost_priors:
                    row["lost_priors"] = lost_frame_priors(used, sequence, configs[mode])
                    print(f"  lost priors: {lost_priors_summary(row['lost_priors'], configs[mode].min_inliers)}", flush=True)
                rows.append(row)
        if args.limits:
            limits[name] = {"ate_cm_by_clock_offset_ms": time_offset_scan(trajectory, sequence.ground_truth),
                            "depth_fit": [depth_fit(frames, sequence, trajectory, gap) for gap in (1, 5)]}
            print(f"  {name} limits: {json.dumps(limits[name])}", flush=True)
    print(format_table(rows))
    for name, cost in costs.items():
        print(f"  {name}: {cost['samples_per_frame']} samples/frame, sampling {cost['sampling_ms']:.2f} ms, "
              f"kernel {cost['kernel_ms_per_step']:.2f} ms per Gauss-Newton step, keyframe maps {cost['keyframe_maps_ms']:.2f} ms")
    atomic_write_text(args.output, json.dumps({"machine": describe_machine(), "overrides": args.set,
                                               "rows": rows, "term_cost": costs, "limits": limits}, indent=2) + "\n")


if __name__ == "__main__":
    main()
