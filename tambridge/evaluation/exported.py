"""The map as a user gets it: ``splats.ply`` reloaded and rendered with no per-view exposure, at the user's poses.

A viewer shows the colours stored in the file; the run's own scores (:mod:`tambridge.evaluation.mapping`) render
through each view's exposure, which no .ply carries. :func:`score_exported` scores what the file shows at the same
novel views, so the two can be compared.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import torch

from tambridge.camera import Camera
from tambridge.evaluation.metrics import ExportedViewScores
from tambridge.evaluation.rendering import score_frames, score_renders, ssim_value
from tambridge.export.splats import load_ply
from tambridge.gaussians.config import MapperConfig
from tambridge.gaussians.model import GaussianTensors, RenderOutput
from tambridge.gaussians.rasterizer import render
from tambridge.io.tum import RgbdSequence
from tambridge.threads import TORCH_THREADS, compute_threads
from tambridge.trajectory import read_tum_trajectory

COVERED_SILHOUETTE = 0.95
"""Pixels whose silhouette reaches this count as covered by the map in the colour ratios."""


@dataclasses.dataclass
class ExportedMap:
    """Gaussians as read from a splats file and the per-frame ``world_from_camera`` (N, 4, 4) poses in the same
    world, rendered by ``backend`` (:data:`tambridge.gaussians.rasterizer.BACKENDS`)."""

    gaussians: GaussianTensors
    world_from_camera: np.ndarray
    backend: str = "auto"

    @classmethod
    def from_run(cls, run_dir: Path, mapper: MapperConfig, device: str | torch.device = "cpu") -> ExportedMap:
        """``run_dir``'s ``splats.ply`` and ``trajectory.txt`` (one pose per frame, in the splats' world)."""
        run_dir = Path(run_dir)
        return cls(load_ply(run_dir / "splats.ply", device),
                   read_tum_trajectory(run_dir / "trajectory.txt").world_from_camera, str(mapper.backend))

    def render(self, camera: Camera, frame_index: int) -> RenderOutput:
        """The splats rendered by ``camera`` at frame ``frame_index``'s pose: what a viewer shows there."""
        return render(self.gaussians, camera, self.world_from_camera[frame_index], backend=self.backend)


def score_exported(exported: ExportedMap, sequence: RgbdSequence, frame_indices: list[int],
                   colour_frames: tuple[int, int], mapper: MapperConfig) -> ExportedViewScores:
    """Scores of ``exported`` at the novel views ``frame_indices`` (full resolution, inside the valid region), its
    SSIM at ``mapper.resolution_scale``, and the colour ratios at ``colour_frames`` (the first and last mapping
    views' frame indices)."""
    camera, scale = sequence.camera, mapper.resolution_scale
    low_resolution_ssim = []

    def with_low_resolution_ssim(pairs):
        for index, rendered, observed in pairs:
            size = (max(1, round(rendered.shape[1] * scale)), max(1, round(rendered.shape[0] * scale)))
            low_resolution_ssim.append(ssim_value(cv2.resize(rendered, size, interpolation=cv2.INTER_AREA),
                                                  cv2.resize(observed, size, interpolation=cv2.INTER_AREA)))
            yield index, rendered, observed

    with compute_threads(TORCH_THREADS, mapper.kernel_threads):
        scores = score_renders(with_low_resolution_ssim(score_frames(sequence, lambda index: exported.render(camera, index).rgb,
                                                                     frame_indices)))
        ratios = [colour_ratio(exported, sequence, index) for index in colour_frames]
    return ExportedViewScores(**scores.summary(),
                              ssim_mapping_resolution=float(np.mean(low_resolution_ssim)) if low_resolution_ssim else None,
                              first_view_colour_ratio=ratios[0], last_view_colour_ratio=ratios[1])


def colour_ratio(exported: ExportedMap, sequence: RgbdSequence, frame_index: int) -> list[float] | None:
    """Per channel (R, G, B), mean render over mean frame at ``frame_index`` where the map covers the valid region
    (None where it covers nothing)."""
    top, bottom, left, right = sequence.valid_region
    output = exported.render(sequence.camera, frame_index)
    covered = (output.silhouette >= COVERED_SILHOUETTE).cpu().numpy()[top:bottom, left:right]
    if not covered.any():
        return None
    rendered = output.rgb.clamp(0.0, 1.0).cpu().numpy()[top:bottom, left:right][covered].astype(np.float64)
    observed = sequence[frame_index].rgb[top:bottom, left:right][covered].astype(np.float64) / 255.0
    return (rendered.mean(axis=0) / np.maximum(observed.mean(axis=0), 1e-6)).tolist()
