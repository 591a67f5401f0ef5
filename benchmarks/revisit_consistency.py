"""How well trajectories fit a sequence's own depth maps where the camera comes back to a place (no ground truth used).

    python benchmarks/revisit_consistency.py out/k/trajectory.txt other/trajectory.txt \
        --camera configs/cameras/7scenes_kinect.yaml            # 7-Scenes redkitchen by default; + its ground truth

Pairs of frames at least ``--min-gap`` frames apart whose ground-truth cameras stand within 0.4 m and look within
20 degrees of each other are revisits (the ground truth only picks the pairs; pass ``--pairs-from`` another
trajectory to pick them without it). ``--pairs`` of them are drawn with a fixed seed. For each pair, every 4th
valid depth pixel of the first frame is lifted, moved into the second frame by a trajectory's relative pose and
projected; its depth is compared with the second frame's depth there (nearest pixel). A trajectory's figure is the
mean over pairs of the median absolute depth difference (mm) and of the share of points within 2 cm: lower and
higher are better, and the ground truth's own poses give the scale of what the sensor allows. Prints a table and
writes benchmarks/results/revisit_consistency.json.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tambridge.camera import Camera  # noqa: E402
from tambridge.files import atomic_write_text  # noqa: E402
from tambridge.geometry import transform_points  # noqa: E402
from tambridge.io.tum import RgbdSequence, open_sequence  # noqa: E402
from tambridge.trajectory import read_tum_trajectory  # noqa: E402

DEFAULT_SEQUENCE = ROOT.parent / "shared" / "data" / "7scenes_redkitchen_0-699"


def revisit_pairs(world_from_camera: np.ndarray, min_gap: int, step: int = 10) -> list[tuple[int, int]]:
    """Frame pairs (i, j), j >= i + min_gap, with camera centres within 0.4 m and optical axes within 20 degrees."""
    pairs = []
    for i in range(0, len(world_from_camera), step):
        for j in range(i + min_gap, len(world_from_camera), step):
            first, second = world_from_camera[i], world_from_camera[j]
            close = np.linalg.norm(first[:3, 3] - second[:3, 3]) < 0.4
            if close and first[:3, 2] @ second[:3, 2] > np.cos(np.radians(20.0)):
                pairs.append((i, j))
    return pairs


def depth_disagreement(first_depth_m: np.ndarray, second_depth_m: np.ndarray, camera: Camera,
                       second_from_first: np.ndarray) -> tuple[float, float]:
    """(median |depth difference| in metres, share within 2 cm) of the first frame's points seen in the second."""
    rows, columns = np.nonzero(first_depth_m > 0)
    rows, columns = rows[::4], columns[::4]
    depth = first_depth_m[rows, columns]
    points = camera.backproject(np.stack([columns, rows], 1), depth)
    moved = transform_points(second_from_first, points)
    in_front = moved[:, 2] > 0.1
    moved = moved[in_front]
    u, v = np.round(camera.project(moved)).astype(int).T
    inside = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    seen = second_depth_m[v[inside], u[inside]]
    difference = np.abs(seen - moved[inside, 2])[seen > 0]
    if difference.size == 0:
        return float("nan"), float("nan")
    return float(np.median(difference)), float((difference < 0.02).mean())


def consistency(sequence: RgbdSequence, world_from_camera: np.ndarray, pairs: list[tuple[int, int]]) -> dict:
    """Mean over ``pairs`` of :func:`depth_disagreement` under the poses ``world_from_camera`` (N, 4, 4)."""
    results = np.array([
        depth_disagreement(sequence.read_depth_m(sequence.depth_paths[i]), sequence.read_depth_m(sequence.depth_paths[j]),
                           sequence.camera, np.linalg.inv(world_from_camera[j]) @ world_from_camera[i])
        for i, j in pairs
    ])
    return {"median_depth_difference_mm": float(np.nanmean(results[:, 0]) * 1000.0),
            "share_within_2cm": float(np.nanmean(results[:, 1]))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("trajectories", nargs="*", type=Path, help="TUM trajectory files, one pose per frame")
    parser.add_argument("--sequence", type=Path, default=DEFAULT_SEQUENCE)
    parser.add_argument("--camera", type=Path, help="camera file the trajectories were made with")
    parser.add_argument("--pairs", type=int, default=40)
    parser.add_argument("--min-gap", type=int, default=60, help="frames between the two frames of a pair")
    parser.add_argument("--pairs-from", type=Path, help="trajectory that picks the pairs (default: ground truth)")
    arguments = parser.parse_args()
    sequence = open_sequence(arguments.sequence, camera_file=arguments.camera, check_depth_scale=False)
    named = {str(path): read_tum_trajectory(path) for path in arguments.trajectories}
    if sequence.ground_truth is not None:
        named["ground truth"] = sequence.ground_truth
    picker = read_tum_trajectory(arguments.pairs_from) if arguments.pairs_from else sequence.ground_truth
    if picker is None:
        parser.error(f"{arguments.sequence} has no groundtruth.txt: pass --pairs-from a trajectory")
    for name, trajectory in [("pairs", picker), *named.items()]:
        if len(trajectory) != len(sequence):
            parser.error(f"{name}: {len(trajectory)} poses for {len(sequence)} frames; one pose per frame is needed")
    candidates = revisit_pairs(picker.world_from_camera, arguments.min_gap)
    rng = np.random.default_rng(0)
    chosen = sorted(candidates[k] for k in rng.choice(len(candidates), min(arguments.pairs, len(candidates)), replace=False))
    rows = [{"trajectory": name, **consistency(sequence, trajectory.world_from_camera, chosen)} for name, trajectory in named.items()]
    print(f"{len(chosen)} revisit pairs of {len(candidates)}, {min(j - i for i, j in chosen)}-{max(j - i for i, j in chosen)} frames apart")
    print("| trajectory | median depth difference mm | share within 2 cm |\n|---|---|---|")
    for row in rows:
        print(f"| {row['trajectory']} | {row['median_depth_difference_mm']:.2f} | {row['share_within_2cm']:.3f} |")
    result = {"sequence": str(arguments.sequence), "camera": str(arguments.camera), "pairs": chosen, "rows": rows}
    atomic_write_text(ROOT / "benchmarks" / "results" / "revisit_consistency.json", json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
