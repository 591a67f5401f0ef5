"""How far independent trajectory estimates lie from each other, beside how far each lies from the ground truth.

    python benchmarks/run_all.py --data ../shared/data                 # first: the runs this reads
    python benchmarks/reference_agreement.py                           # 7-Scenes redkitchen 0-699

7-Scenes' ground truth is KinectFusion's trajectory (depth-only ICP against a TSDF), a pseudo ground truth: Brachmann
et al. (ICCV 2021, "On the limits of pseudo ground truth in visual camera re-localisation") showed that on 7-Scenes
the ranking of methods changes when the reference is SfM instead, and that depth-based methods are favoured by the
depth-based reference. This measures that here. Every estimate is taken at the frames COLMAP registered (every 5th)
and Sim(3)-aligned, since COLMAP's scale is free. If two estimates that share no algorithm (tambridge's RGB-D ORB
with BA, and COLMAP's SIFT incremental SfM on colour alone) agree far better than either agrees with the ground
truth, and their errors against it point the same way, the remaining ATE is a property of the reference (or of the
camera model every method shares), not of the tracker.

How the camera model every method shares moves the figure (the focal lengths of the depth and colour cameras):
`camera_sweep.py`. Prints tables and writes benchmarks/results/reference_agreement.json.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tambridge.evaluation.trajectory import evaluate_trajectory  # noqa: E402
from tambridge.files import atomic_write_text  # noqa: E402
from tambridge.trajectory import Trajectory, read_tum_trajectory  # noqa: E402

RUNS = ROOT / "benchmarks" / "results" / "runs"
DEFAULT_SEQUENCE = ROOT.parent / "shared" / "data" / "7scenes_redkitchen_0-699"
# run_all's output folders (under RUNS, prefixed with the sequence name) of the estimates compared.
ESTIMATES = {
    "tambridge ORB": "tambridge_default",
    "tambridge Open3D frontend": "tambridge_open3d_frontend",
    "COLMAP": "COLMAP",
}
MONOCULAR = {"COLMAP"}


def offsets_from_reference_m(estimate: Trajectory, reference: Trajectory) -> np.ndarray:
    """(N, 3) positions of ``estimate`` minus ``reference``'s, after a Sim(3) alignment onto ``reference``."""
    errors = evaluate_trajectory(estimate, reference, align="sim3")
    return errors.aligned_est.positions_m - errors.ref.positions_m


def agreement(trajectories: dict[str, Trajectory], ground_truth: Trajectory) -> dict:
    """Pairwise Sim(3) ATE (cm) among the estimates and the ground truth, and how alike their errors are.

    ``trajectories`` are taken at the same frames; those in ``MONOCULAR`` are the ones scaled in each pair.
    ``error_correlation`` [a][b] is the correlation of a's and b's position offsets from the ground truth (1: they
    miss it the same way).
    """
    named = {**trajectories, "ground truth": ground_truth}

    def distance_cm(a: str, b: str) -> float:
        # The trajectory without a metric scale is the one aligned, so that the figure is in metres.
        estimate, reference = (b, a) if b in MONOCULAR else (a, b)
        return 100.0 * evaluate_trajectory(named[estimate], named[reference], align="sim3").ate_rmse_m

    ate_cm = {a: {b: (0.0 if a == b else distance_cm(a, b)) for b in named} for a in named}
    offsets = {name: offsets_from_reference_m(trajectory, ground_truth) for name, trajectory in trajectories.items()}
    correlation = {a: {b: float(np.corrcoef(offsets[a].ravel(), offsets[b].ravel())[0, 1]) for b in offsets}
                   for a in offsets}
    return {"ate_cm": ate_cm, "error_correlation": correlation}


def print_matrix(title: str, matrix: dict, format_spec: str) -> None:
    columns = list(next(iter(matrix.values())))
    print(f"\n{title}\n| | " + " | ".join(columns) + " |\n|---|" + "---|" * len(columns))
    for name, row in matrix.items():
        print(f"| {name} | " + " | ".join(format(row[column], format_spec) for column in columns) + " |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sequence", type=Path, default=DEFAULT_SEQUENCE)
    parser.add_argument("--runs", type=Path, default=RUNS, help="run_all's output folders")
    arguments = parser.parse_args()
    sequence = arguments.sequence
    ground_truth = read_tum_trajectory(sequence / "groundtruth.txt")
    paths = {name: arguments.runs / f"{sequence.name}__{folder}" / "trajectory.txt" for name, folder in ESTIMATES.items()}
    missing = [str(path) for path in paths.values() if not path.is_file()]
    if missing:
        parser.error(f"missing {', '.join(missing)}: run 'python benchmarks/run_all.py --data {sequence.parent}' first")
    trajectories = {name: read_tum_trajectory(path) for name, path in paths.items()}
    frames_s = trajectories["COLMAP"].timestamps_s
    trajectories = {name: trajectory.nearest(frames_s) for name, trajectory in trajectories.items()}
    result = {"sequence": str(sequence), "frames": len(frames_s), **agreement(trajectories, ground_truth.nearest(frames_s))}
    print(f"{sequence.name}: {len(frames_s)} frames (those COLMAP registered), Sim(3)-aligned")
    print_matrix("ATE RMSE between trajectories (cm), the row's aligned onto the column's", result["ate_cm"], ".2f")
    print_matrix("correlation of position errors against the ground truth", result["error_correlation"], ".3f")
    atomic_write_text(ROOT / "benchmarks" / "results" / "reference_agreement.json", json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
