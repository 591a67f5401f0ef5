"""How upright a finished run's exported world is: its up against the ground truth's, and the map's planes in it.

    python benchmarks/upright_world.py out/fr1_xyz --truth-up z     # TUM: the motion capture's z is up
    python benchmarks/upright_world.py out/kitchen                  # 7-Scenes: its pseudo ground truth has no up

For each run folder (a ``tambridge reconstruct`` output, default ``export.world=upright``): how up was found
(metrics.json), and, with ``--truth-up AXIS``, the angle between the upright world's z and the ground truth's AXIS
(the run's orientations rotated onto the truth's). The estimators are also run on the run's own data, as the run had them in its
first camera's frame: the accelerometer (where the folder has accelerometer.txt), the floor of mesh.ply near the
accelerometer's up (the run's choice where there is one), and the planes of mesh.ply alone. The
check that needs no ground truth: the planes of the exported mesh.ply (RANSAC, :func:`dominant_planes`) split into
floors (normal within 45 degrees of z; their tilt from level) and walls (their lean from plumb), each with its share
of the mesh's vertices. Prints a table and writes benchmarks/results/upright_world.json.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tambridge.evaluation.metrics import read_metrics  # noqa: E402
from tambridge.export.mesh import read_mesh  # noqa: E402
from tambridge.export.world import (  # noqa: E402
    FLOOR_NEAR_ACCELEROMETER_DEG,
    FLOOR_WITHIN_DEG,
    camera_up,
    dominant_planes,
    up_from_accelerometer,
    up_from_floor,
    up_from_planes,
)
from tambridge.files import atomic_write_text  # noqa: E402
from tambridge.geometry import inverse, rotation_onto, transform_points  # noqa: E402
from tambridge.io.tum import find_accelerometer  # noqa: E402
from tambridge.trajectory import Trajectory, read_tum_trajectory  # noqa: E402

AXES = {"x": 0, "y": 1, "z": 2}


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1.0, 1.0))))


def truth_up_in_upright(trajectory: Trajectory, truth: Trajectory, axis: str) -> np.ndarray:
    """The ground truth's ``axis`` in the run's upright world, through the rotation that best maps the run's camera
    orientations onto the truth's at the same times (the chordal mean of ``R_truth R_run^T``: the ATE's alignment
    fits positions only, which leaves a rotation about a short path's line free)."""
    nearest = truth.nearest(trajectory.timestamps_s)
    near = np.abs(nearest.timestamps_s - trajectory.timestamps_s) <= 0.02
    truth_from_upright = rotation_onto(nearest.world_from_camera[near, :3, :3],
                                       trajectory.world_from_camera[near, :3, :3])
    return truth_from_upright.T @ np.eye(3)[AXES[axis]]


def plane_check(vertices_m: np.ndarray) -> dict:
    """The mesh's planes in the upright world: floors' tilt from level and walls' lean from plumb (degrees)."""
    planes = dominant_planes(vertices_m)
    floors, walls = [], []
    for plane in planes:
        share = plane.inliers / len(vertices_m)
        from_z = angle_deg(plane.normal if plane.normal[2] >= 0 else -plane.normal, np.array([0.0, 0.0, 1.0]))
        if from_z <= FLOOR_WITHIN_DEG:
            floors.append({"tilt_deg": from_z, "share": share, "height_m": float(plane.centre_m[2])})
        else:
            walls.append({"lean_deg": abs(90.0 - from_z), "share": share})
    return {"floors": floors, "walls": walls}


def measure(run_dir: Path, truth_up: str | None) -> dict:
    metrics = read_metrics(run_dir / "metrics.json")
    upright_from_first = np.array(metrics.world.upright_from_first_camera)
    first_from_upright = inverse(upright_from_first)
    trajectory = read_tum_trajectory(run_dir / "trajectory.txt")
    mesh = read_mesh(run_dir / "mesh.ply")
    sequence = Path(metrics.sequence)
    row = {"run": str(run_dir), "sequence": sequence.name, "frames": metrics.frames, "up_source": metrics.world.up_source,
           "tilt_of_first_camera_deg": angle_deg(first_from_upright[:3, 2], np.array([0.0, -1.0, 0.0]))
           if metrics.world.up_source != "first_camera" else 0.0}
    # The estimators on the run's data in its first camera's frame, as the run had it.
    trajectory_first = Trajectory(trajectory.timestamps_s, first_from_upright @ trajectory.world_from_camera)
    vertices_first = transform_points(first_from_upright, np.asarray(mesh.vertices, np.float64))
    estimates = {}
    accelerometer = find_accelerometer(sequence)
    mesh_planes = dominant_planes(vertices_first)
    if accelerometer is not None:
        estimates["accelerometer"] = up_from_accelerometer(accelerometer, trajectory_first)
        floor = up_from_floor(mesh_planes, estimates["accelerometer"], FLOOR_NEAR_ACCELEROMETER_DEG)
        if floor is not None:
            estimates["accelerometer_floor"] = floor
    planes = up_from_planes(mesh_planes, camera_up(trajectory_first.world_from_camera))
    if planes is not None:
        estimates[str(planes[1])] = planes[0]
    estimates["first_camera"] = np.array([0.0, -1.0, 0.0])
    if truth_up is not None and metrics.sequence and (sequence / "groundtruth.txt").is_file():
        truth = read_tum_trajectory(sequence / "groundtruth.txt")
        up_upright = truth_up_in_upright(trajectory, truth, truth_up)
        # The exported world's up: z, or the first camera's image up where the files stay in its frame.
        exported_up = np.array([0.0, -1.0, 0.0]) if np.array_equal(upright_from_first, np.eye(4)) else np.eye(3)[2]
        row["angle_to_truth_up_deg"] = angle_deg(up_upright, exported_up)
        up_first = first_from_upright[:3, :3] @ up_upright
        row["estimates_angle_to_truth_up_deg"] = {name: angle_deg(up, up_first) for name, up in estimates.items()}
    row["mesh_planes"] = plane_check(np.asarray(mesh.vertices, np.float64))
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="reconstruct output folders")
    parser.add_argument("--truth-up", choices=sorted(AXES), help="the ground truth's up axis (TUM: z); omit where it has none")
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks" / "results" / "upright_world.json")
    arguments = parser.parse_args()
    rows = [measure(run, arguments.truth_up) for run in arguments.runs]
    print(f"{'sequence':32s} {'frames':>6s} {'up from':>14s} {'to truth':>9s} {'1st cam':>8s}  floors tilt/share   walls lean/share")
    for row in rows:
        to_truth = row.get("angle_to_truth_up_deg")
        floors = " ".join(f"{f['tilt_deg']:.1f}/{f['share']:.2f}" for f in row["mesh_planes"]["floors"])
        walls = " ".join(f"{w['lean_deg']:.1f}/{w['share']:.2f}" for w in row["mesh_planes"]["walls"])
        print(f"{row['sequence']:32s} {row['frames']:6d} {row['up_source']:>14s} "
              f"{'-' if to_truth is None else f'{to_truth:.2f}':>9s} {row['tilt_of_first_camera_deg']:8.1f}  {floors:18s} {walls}")
        for name, angle in row.get("estimates_angle_to_truth_up_deg", {}).items():
            print(f"    {name:>14s} alone: {angle:.2f} degrees from the truth's up")
    existing = json.loads(arguments.output.read_text()) if arguments.output.is_file() else {}
    existing.update({row["sequence"]: row for row in rows})
    atomic_write_text(arguments.output, json.dumps(existing, indent=2) + "\n")


if __name__ == "__main__":
    main()
