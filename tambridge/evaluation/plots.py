"""Trajectory plots (matplotlib, Agg backend): top view of estimates against the reference, ATE over time."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from tambridge.evaluation.trajectory import WORST_WINDOW_S, TrajectoryErrors, worst_error_window  # noqa: E402
from tambridge.files import atomic_path  # noqa: E402


def _top_view_axes(positions_m: np.ndarray) -> tuple[int, int]:
    """The two world axes along which the reference moves most: the 'top view' for any gravity direction."""
    spread = positions_m.max(axis=0) - positions_m.min(axis=0)
    first, second = sorted(np.argsort(spread)[-2:])
    return int(first), int(second)


def plot_trajectory_errors(results: dict[str, TrajectoryErrors], path: Path, title: str = "") -> None:
    """Write one PNG: left, top view of each aligned estimate and the reference; right, ATE over time with the
    first estimate's worst :data:`WORST_WINDOW_S`-second window shaded."""
    figure, (top, over_time) = plt.subplots(1, 2, figsize=(12, 5))
    reference = next(iter(results.values())).ref
    axis_a, axis_b = _top_view_axes(reference.positions_m)
    names = "xyz"
    top.plot(reference.positions_m[:, axis_a], reference.positions_m[:, axis_b], "k--", label="ground truth")
    for name, errors in results.items():
        positions = errors.aligned_est.positions_m
        top.plot(positions[:, axis_a], positions[:, axis_b], label=f"{name} ({errors.ate_rmse_m * 100:.2f} cm)")
        over_time.plot(errors.timestamps_s - errors.timestamps_s[0], errors.ate_errors_m * 100.0, label=name)
    first = next(iter(results.values()))
    worst = worst_error_window(first.timestamps_s, first.ate_errors_m, WORST_WINDOW_S)
    origin_s = first.timestamps_s[0]
    over_time.axvspan(worst.start_s - origin_s, worst.end_s - origin_s, color="red", alpha=0.15,
                      label=f"worst {WORST_WINDOW_S:g} s ({worst.rmse_m * 100:.2f} cm RMSE)")
    top.set_xlabel(f"{names[axis_a]} [m]")
    top.set_ylabel(f"{names[axis_b]} [m]")
    top.set_aspect("equal", adjustable="datalim")
    top.legend(fontsize=8)
    top.set_title("top view (aligned)")
    over_time.set_xlabel("time [s]")
    over_time.set_ylabel("ATE [cm]")
    over_time.legend(fontsize=8)
    over_time.set_title("absolute trajectory error")
    if title:
        figure.suptitle(title)
    figure.tight_layout()
    with atomic_path(Path(path)) as temp_path:
        figure.savefig(temp_path, format="png", dpi=100)
    plt.close(figure)
