"""``tambridge compare``: several trajectories against one ground truth, in one table and one plot.

Each estimate is aligned with Sim(3) when it is monocular (COLMAP's files say so in their header, or the
caller names it) and with SE(3) otherwise; ATE and RPE then come from
:func:`tambridge.evaluation.trajectory.evaluate_trajectory`.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Sequence

from tambridge.errors import TrajectoryFormatError
from tambridge.evaluation.colmap import is_monocular_trajectory_file
from tambridge.evaluation.plots import plot_trajectory_errors
from tambridge.evaluation.trajectory import Alignment, TrajectoryErrors, evaluate_trajectory
from tambridge.trajectory import Trajectory, read_tum_trajectory


@dataclasses.dataclass
class Comparison:
    """One row per estimate, in the order given: its name and its errors (alignment included)."""

    errors: dict[str, TrajectoryErrors]

    def rows(self) -> list[dict]:
        """Table rows: name, alignment, poses, ATE RMSE/max (cm), RPE translation (cm/frame), rotation (deg/frame), scale."""
        return [
            {
                "name": name,
                "alignment": errors.alignment,
                "poses": errors.pose_count,
                "ate_rmse_cm": errors.ate_rmse_m * 100.0,
                "ate_max_cm": errors.ate_max_m * 100.0,
                "rpe_trans_cm": errors.rpe_trans_rmse_m * 100.0,
                "rpe_rot_deg": errors.rpe_rot_rmse_deg,
                "scale": errors.scale,
            }
            for name, errors in self.errors.items()
        ]

    def table(self) -> str:
        """The rows as an aligned plain-text table."""
        header = ["trajectory", "align", "poses", "ATE RMSE [cm]", "ATE max [cm]", "RPE [cm/frame]", "RPE [deg/frame]", "scale"]
        lines = [
            [row["name"], row["alignment"], str(row["poses"]), f"{row['ate_rmse_cm']:.2f}", f"{row['ate_max_cm']:.2f}",
             f"{row['rpe_trans_cm']:.2f}", f"{row['rpe_rot_deg']:.3f}", f"{row['scale']:.4f}"]
            for row in self.rows()
        ]
        widths = [max(len(cell) for cell in column) for column in zip(header, *lines)]
        return "\n".join("  ".join(cell.ljust(width) for cell, width in zip(line, widths)).rstrip() for line in [header, *lines])


def compare(
    traj_ref: Trajectory, estimates: dict[str, tuple[Trajectory, Alignment]], plot_path: Path | None = None, title: str = ""
) -> Comparison:
    """Evaluate each named ``(trajectory, alignment)`` against ``traj_ref``; write one plot of all when asked."""
    errors = {}
    for name, (trajectory, align) in estimates.items():
        try:
            errors[name] = evaluate_trajectory(trajectory, traj_ref, align)
        except ValueError as error:
            raise TrajectoryFormatError(f"{name}: {error}") from error
    comparison = Comparison(errors)
    if plot_path is not None and errors:
        plot_trajectory_errors(errors, Path(plot_path), title=title)
    return comparison


def _names(name: str, path: Path) -> bool:
    """Whether a ``--sim3`` name means the file ``path``: its stem, or a path to the same file."""
    return name == path.stem or Path(name).resolve() == path.resolve()


def compare_files(
    ground_truth: Path, estimate_paths: Sequence[Path], sim3_names: Sequence[str] = (), plot_path: Path | None = None
) -> Comparison:
    """Compare TUM files against a ground-truth file; Sim(3) for files marked monocular or named in ``sim3_names``.

    A name in ``sim3_names`` matches a file by its path (however written: ``./a/t.txt`` is ``a/t.txt``) or its stem.
    Rows are named by the files' paths.
    """
    estimates = {}
    for path in estimate_paths:
        path = Path(path)
        monocular = any(_names(name, path) for name in sim3_names) or is_monocular_trajectory_file(path)
        estimates[str(path)] = (read_tum_trajectory(path), "sim3" if monocular else "se3")
    if len(set(estimates)) != len(estimate_paths):
        names = [str(Path(path)) for path in estimate_paths]
        twice = next(name for name in names if names.count(name) > 1)
        raise TrajectoryFormatError(f"{twice}: named twice; give each trajectory once")
    unknown = [name for name in sim3_names if not any(_names(name, Path(key)) for key in estimates)]
    if unknown:
        raise TrajectoryFormatError(f"--sim3 {unknown[0]!r} names none of the trajectories given "
                                    f"({', '.join(estimates)}); give one's path or its file name without .txt")
    for name in sim3_names:
        named = [key for key in estimates if _names(name, Path(key))]
        if len(named) > 1:
            raise TrajectoryFormatError(f"--sim3 {name!r} names {len(named)} of the trajectories ({', '.join(named)}); "
                                        "give the path of the one meant")
    if any(Path(path).resolve() == Path(ground_truth).resolve() for path in estimate_paths):
        raise TrajectoryFormatError(f"{ground_truth}: is the ground truth (--gt) and an estimate too; give it once")
    return compare(read_tum_trajectory(ground_truth), estimates, plot_path, title=f"against {ground_truth}")
