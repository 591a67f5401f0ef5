"""Scores of a run's Gaussian map: rendering quality at novel and mapping views, map and bridge figures."""

from __future__ import annotations

import logging

import numpy as np
import torch

from tambridge.evaluation.config import EvaluationConfig
from tambridge.evaluation.exported import ExportedMap, score_exported
from tambridge.evaluation.rendering import RenderingScores, score_frames, score_renders
from tambridge.evaluation.metrics import (
    BridgeMetrics,
    MapMetrics,
    RenderingMetrics,
    ScoredAgainst,
    ViewPoseErrors,
    ViewScores,
)
from tambridge.errors import TrajectoryEvaluationError
from tambridge.evaluation.trajectory import ate_rmse_m
from tambridge.frontend.contract import FrontendResult
from tambridge.images import sharpness
from tambridge.io.tum import RgbdSequence
from tambridge.mapping.stage import MappingStage
from tambridge.runlog import RunLog
from tambridge.trajectory import Trajectory

logger = logging.getLogger("tambridge.evaluation.mapping")


def evaluation_frames(frame_count: int, every: int, mapping_frames: set[int]) -> list[int]:
    """Novel views: every ``every``-th frame (0, every, 2 every, ...) that is not a mapping view."""
    return [index for index in range(0, frame_count, every) if index not in mapping_frames]


def score_views(mapping: MappingStage, rendering_poses: np.ndarray, frame_indices: list[int],
                against_sharp: bool = True) -> RenderingScores:
    """PSNR/SSIM/LPIPS (:func:`score_frames`, against the sharp ground truth where the sequence has it and
    ``against_sharp``) of the map rendered from ``rendering_poses`` (N, 4, 4) through the exposure of each frame's
    anchor view (estimated from mapping views only)."""
    def render_rgb(index: int) -> torch.Tensor:
        rendered = mapping.map.render(mapping.sequence.camera, rendering_poses[index]).rgb
        exposure = mapping.anchor_view(index).exposure if mapping.views else None
        return rendered if exposure is None else exposure.apply(rendered)

    with mapping.threads():
        return score_renders(score_frames(mapping.sequence, render_rgb, frame_indices, against_sharp))


def sharper_half(sequence: RgbdSequence, frame_indices: list[int]) -> list[int]:
    """The half (rounded up) of ``frame_indices`` whose input frames score highest on
    :func:`~tambridge.images.sharpness`, in their given order: where a map sharper than its blurred inputs is
    not punished for differing from them."""
    scores = np.array([sharpness(sequence[index].rgb) for index in frame_indices])
    keep = np.argsort(-scores, kind="stable")[: (len(frame_indices) + 1) // 2]
    return [frame_indices[position] for position in sorted(keep)]


def scores_of_frames(scores: RenderingScores, frame_indices: list[int]) -> RenderingScores:
    """The per-frame scores of ``frame_indices``, each one of ``scores.frame_indices``."""
    positions = [scores.frame_indices.index(index) for index in frame_indices]
    return RenderingScores(list(frame_indices), [scores.psnr_db[i] for i in positions], [scores.ssim[i] for i in positions],
                           None if scores.lpips is None else [scores.lpips[i] for i in positions])


def blur_aware_scores(mapping: MappingStage, rendering_poses: np.ndarray, novel: RenderingScores) -> dict:
    """The rendering fields about blur (see :class:`RenderingMetrics`) for the novel views' ``novel`` scores: what
    they were scored against, their sharper half, and with sharp ground truth the scores against the inputs."""
    sequence = mapping.sequence
    return dict(
        scored_against=ScoredAgainst.sharp_ground_truth if sequence.has_sharp_rgb else ScoredAgainst.input,
        novel_views_sharper_half=ViewScores(**scores_of_frames(novel, sharper_half(sequence, novel.frame_indices)).summary()),
        novel_views_against_input=ViewScores(**score_views(mapping, rendering_poses, novel.frame_indices,
                                                           against_sharp=False).summary())
        if sequence.has_sharp_rgb else None,
    )


def mapping_metrics(mapping: MappingStage, tracking: FrontendResult, sequence: RgbdSequence, evaluation: EvaluationConfig,
                    run_log: RunLog, exported: ExportedMap) -> MapMetrics:
    """What the mapping stage adds to metrics.json: rendering scores (novel and mapping views), map and bridge figures.

    Renders are at full resolution from the rendering poses (the bridge-refined views and the frames anchored on
    them) through the views' exposures; the novel views are scored again as ``exported`` shows them
    (:func:`score_exported`). With ground truth, the ATE of the mapping views' poses before (frontend) and after
    the bridge is added.
    """
    poses = mapping.rendering_poses(tracking.trajectory)
    view_frames = sorted(view.frame_index for view in mapping.views)
    novel = evaluation_frames(len(sequence), evaluation.novel_view_every, set(view_frames))
    with run_log.stage("evaluation"):
        novel_per_frame = score_views(mapping, poses, novel)
        novel_scores = ViewScores(**novel_per_frame.summary())
        view_scores = ViewScores(**score_views(mapping, poses, view_frames).summary())
        blur_scores = blur_aware_scores(mapping, poses, novel_per_frame)
        exported_scores = score_exported(exported, sequence, novel, (view_frames[0], view_frames[-1]) if view_frames else (0, 0),
                                         mapping.mapper_config)
    refinements = [view.refinement for view in mapping.views if view.refinement is not None and not view.refinement.skipped]
    blurred = [count for count in mapping.subposes.values() if count > 1]
    logger.info("rendering: novel views %.2f dB PSNR, %.3f SSIM (%d frames); mapping views %.2f dB, %.3f SSIM (%d); %d Gaussians",
                novel_scores.psnr_db or float("nan"), novel_scores.ssim or float("nan"), len(novel),
                view_scores.psnr_db or float("nan"), view_scores.ssim or float("nan"), len(view_frames), len(mapping.map))
    logger.info("as exported (no exposure, trajectory.txt's poses): novel views %.2f dB PSNR, %.3f SSIM; colour ratio "
                "render / frame at the first view %s, at the last %s", exported_scores.psnr_db or float("nan"),
                exported_scores.ssim or float("nan"), _rounded(exported_scores.first_view_colour_ratio),
                _rounded(exported_scores.last_view_colour_ratio))
    exposures = [view.exposure.parameters.detach().cpu().numpy() for view in mapping.views if view.exposure is not None]
    if exposures:
        gains, biases = np.exp(np.stack(exposures)[:, 0]), np.stack(exposures)[:, 1]
        logger.info("view exposures: gains %.3f to %.3f, biases %+.3f to %+.3f (over views and channels)", gains.min(),
                    gains.max(), biases.min(), biases.max())
    views_ate = None
    if sequence.ground_truth is not None and len(view_frames) >= 3:
        timestamps = sequence.timestamps_s[view_frames]
        frontend_poses = tracking.trajectory.world_from_camera[view_frames]
        try:
            views_ate = ViewPoseErrors(
                frontend=ate_rmse_m(Trajectory(timestamps, frontend_poses), sequence.ground_truth, align="se3"),
                rendering=ate_rmse_m(Trajectory(timestamps, poses[view_frames]), sequence.ground_truth, align="se3"),
            )
        except TrajectoryEvaluationError as error:
            # The run's metrics say why there is no ATE (trajectory_unavailable); the map's scores stand without it.
            logger.info("no ATE of the mapping views: %s", error)
    return MapMetrics(
        rendering=RenderingMetrics(novel_views=novel_scores, mapping_views=view_scores, novel_views_exported=exported_scores,
                                   **blur_scores),
        gaussians=len(mapping.map),
        mapping_views=len(mapping.views),
        mapping_resolution=[mapping.camera.width, mapping.camera.height],
        bridge=BridgeMetrics(
            enabled=mapping.bridge_config.enabled,
            view_selection=dict(mapping.selections),
            refined_views=len(refinements),
            mean_loss_initial=float(np.mean([r.loss_initial for r in refinements])) if refinements else None,
            mean_loss_final=float(np.mean([r.loss_final for r in refinements])) if refinements else None,
            views_ate_rmse_m=views_ate,
            blur_exposure_s=mapping.blur_exposure_s,
            blurred_views=len(blurred),
            mean_subposes_blurred=float(np.mean(blurred)) if blurred else None,
        ),
    )


def _rounded(ratio: list[float] | None) -> str:
    return "-" if ratio is None else "/".join(f"{value:.3f}" for value in ratio)
