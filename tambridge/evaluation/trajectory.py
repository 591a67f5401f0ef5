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
