"""Trajectory error: ATE after SE(3)/Sim(3) Umeyama alignment and RPE, computed with evo (the field's standard)."""

from __future__ import annotations

import copy
import dataclasses
from typing import Literal

import numpy as np
from evo.core import metrics, sync
from evo.core.geometry import GeometryException
from evo.core.trajectory import PoseTrajectory3D

from tambridge.errors import TrajectoryEvaluationError
from tambridge.trajectory import Trajectory

Alignment = Literal["se3", "sim3", "none"]
MAX_TIME_DIFFERENCE_S = 0.02
TIME_TOLERANCE_S = 1e-6  # TUM's timestamps have microseconds; sums of k/30 s must not fall out of a window
WORST_WINDOW_S = 2.0
"""The span of :func:`worst_error_window` in reports: long enough to hold a fast turn, short against a sequence."""


@dataclasses.dataclass
class TrajectoryErrors:
    """ATE and RPE of an estimate against a reference, after alignment.

    ``ate_errors_m`` (N,) per associated pose; ``aligned_est`` is the estimate moved onto the reference,
    ``ref`` the reference poses at the same times. ``rpe_*`` are translational errors between consecutive
    associated poses (delta of one pose, metres) and rotational ones (degrees).
    """

    alignment: Alignment
    pose_count: int
    ate_rmse_m: float
    ate_mean_m: float
    ate_median_m: float
    ate_max_m: float
    rpe_trans_rmse_m: float
    rpe_rot_rmse_deg: float
    scale: float
    ate_errors_m: np.ndarray
    timestamps_s: np.ndarray
    aligned_est: Trajectory
    ref: Trajectory

    def summary(self) -> dict:
        """JSON-ready scalars."""
        return {
            "alignment": self.alignment,
            "pose_count": self.pose_count,
            "ate_rmse_m": self.ate_rmse_m,
            "ate_mean_m": self.ate_mean_m,
            "ate_median_m": self.ate_median_m,
            "ate_max_m": self.ate_max_m,
            "rpe_trans_rmse_m": self.rpe_trans_rmse_m,
            "rpe_rot_rmse_deg": self.rpe_rot_rmse_deg,
            "scale": self.scale,
        }


def _to_evo(trajectory: Trajectory) -> PoseTrajectory3D:
    return PoseTrajectory3D(poses_se3=list(trajectory.world_from_camera), timestamps=trajectory.timestamps_s)


def _from_evo(trajectory: PoseTrajectory3D) -> Trajectory:
    return Trajectory(np.asarray(trajectory.timestamps), np.stack(trajectory.poses_se3))


def _span(trajectory: Trajectory) -> str:
    """The time span of a trajectory, for messages."""
    if not len(trajectory):
        return "empty"
    return f"{trajectory.timestamps_s[0]:.3f}..{trajectory.timestamps_s[-1]:.3f} s"


def evaluate_trajectory(
    traj_est: Trajectory,
    traj_ref: Trajectory,
    align: Alignment = "se3",
    max_time_difference_s: float = MAX_TIME_DIFFERENCE_S,
) -> TrajectoryErrors:
    """Associate by timestamp, align the estimate to the reference (Umeyama 1991) and compute ATE and RPE.

    ``align="sim3"`` also estimates scale (monocular trajectories); ``"none"`` compares as given.
    """
    if len(traj_est) < 3:
        raise TrajectoryEvaluationError(f"the estimate has {len(traj_est)} poses; ATE needs at least 3 (an alignment "
                                        "is fitted to them)")
    try:
        evo_ref, evo_est = sync.associate_trajectories(_to_evo(traj_ref), _to_evo(traj_est), max_diff=max_time_difference_s)
    except sync.SyncException:
        evo_est = None
    matched = 0 if evo_est is None else evo_est.num_poses
    if matched < 3:
        raise TrajectoryEvaluationError(
            f"only {matched} of {len(traj_est)} estimated poses lie within {max_time_difference_s} s of a reference "
            f"pose (estimate {_span(traj_est)}, reference {_span(traj_ref)}); check that both use the same clock and "
            "cover the same frames"
        )
    evo_est = copy.deepcopy(evo_est)
    scale = 1.0
    if align != "none":
        try:
            _, _, scale = evo_est.align(evo_ref, correct_scale=(align == "sim3"))
        except GeometryException as error:
            raise TrajectoryEvaluationError(f"the {matched} matched poses cannot be aligned ({error}); the camera "
                                            "barely moved or moved along a line") from None
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((evo_ref, evo_est))
    rpe_trans = metrics.RPE(metrics.PoseRelation.translation_part, delta=1, delta_unit=metrics.Unit.frames)
    rpe_trans.process_data((evo_ref, evo_est))
    rpe_rot = metrics.RPE(metrics.PoseRelation.rotation_angle_deg, delta=1, delta_unit=metrics.Unit.frames)
    rpe_rot.process_data((evo_ref, evo_est))
    statistic = metrics.StatisticsType
    return TrajectoryErrors(
        alignment=align,
        pose_count=evo_est.num_poses,
        ate_rmse_m=float(ape.get_statistic(statistic.rmse)),
        ate_mean_m=float(ape.get_statistic(statistic.mean)),
        ate_median_m=float(ape.get_statistic(statistic.median)),
        ate_max_m=float(ape.get_statistic(statistic.max)),
        rpe_trans_rmse_m=float(rpe_trans.get_statistic(statistic.rmse)),
        rpe_rot_rmse_deg=float(rpe_rot.get_statistic(statistic.rmse)),
        scale=float(scale),
        ate_errors_m=np.asarray(ape.error),
        timestamps_s=np.asarray(evo_est.timestamps),
        aligned_est=_from_evo(evo_est),
        ref=_from_evo(evo_ref),
    )


def ate_rmse_m(traj_est: Trajectory, traj_ref: Trajectory, align: Alignment = "se3") -> float:
    """ATE RMSE in metres after alignment: the headline number of a trajectory."""
    return evaluate_trajectory(traj_est, traj_ref, align).ate_rmse_m


@dataclasses.dataclass(frozen=True)
class ErrorWindow:
    """A span of associated poses: ``first``..``last`` (inclusive indices into the evaluated poses, which are the
    frames in order where every frame had a reference pose), their timestamps (s, the sequence's clock) and the
    RMSE of the translational errors inside (m)."""

    first: int
    last: int
    start_s: float
    end_s: float
    rmse_m: float

    def describe(self, origin_s: float) -> str:
        """One line for reports; times relative to ``origin_s``."""
        return (f"poses {self.first}-{self.last}, {self.start_s - origin_s:.1f}-{self.end_s - origin_s:.1f} s "
                f"(timestamps {self.start_s:.3f}-{self.end_s:.3f}): RMSE {self.rmse_m * 100:.2f} cm")


def worst_error_window(timestamps_s: np.ndarray, errors_m: np.ndarray, window_s: float = WORST_WINDOW_S) -> ErrorWindow:
    """The window of at most ``window_s`` seconds (poses ``i..j`` with ``t_j - t_i <= window_s``, as long as they
    reach) whose per-pose errors ``errors_m`` (N,) at increasing ``timestamps_s`` (N,) have the highest RMSE; the
    whole trajectory when it is shorter. Windows start at poses; ties go to the earliest."""
    timestamps_s, errors_m = np.asarray(timestamps_s, np.float64), np.asarray(errors_m, np.float64)
    if len(timestamps_s) == 0 or len(timestamps_s) != len(errors_m):
        raise ValueError(f"worst_error_window: {len(timestamps_s)} timestamps for {len(errors_m)} errors")
    squared = np.concatenate([[0.0], np.cumsum(errors_m**2)])
    first = np.arange(len(timestamps_s))
    # Last pose of each window: the latest within window_s of its first (every window holds its first pose).
    reach_s = window_s + TIME_TOLERANCE_S
    last = np.searchsorted(timestamps_s, timestamps_s + reach_s, side="right") - 1
    rmse = np.sqrt((squared[last + 1] - squared[first]) / (last - first + 1))
    # Windows cut short by the end are left out (the last full one covers their poses), unless none is full.
    if timestamps_s[-1] - timestamps_s[0] + TIME_TOLERANCE_S >= window_s:
        full = timestamps_s <= timestamps_s[-1] - window_s + TIME_TOLERANCE_S
    else:
        full = first == 0
    best = int(np.argmax(np.where(full, rmse, -1.0)))
    return ErrorWindow(best, int(last[best]), float(timestamps_s[best]), float(timestamps_s[last[best]]),
                       float(rmse[best]))
