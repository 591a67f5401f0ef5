"""The mapping stage of ``reconstruct``: keyframe events -> Fusion Bridge -> online Gaussian map, then evaluation.

``MappingStage.on_keyframe`` runs online, as the frontend emits keyframes: view selection (eq. 3), joint pose
refinement against the current map, densification, a few Adam steps over a window of overlapping views, pruning.
Coverage (``mapper.coverage_unexplained``): ``MappingStage.needs_view`` renders the map at some tracked frames
between keyframes and says when one shows too much the map does not explain; the pipeline then asks the frontend
for a keyframe, and such a keyframe is mapped even where eq. 3 finds it too similar to the previous one.
``MappingStage.finish`` moves every view to the frontend's final (loop-corrected) keyframe poses and runs a last
pass over all views, then a sharpening pass at the camera's resolution over the views and some tracked frames
between them (never one the evaluation holds out). Frames are not kept while tracking: a small cache holds the
window's images at the mapping resolution and anything else is read again from the sequence; the sharpening pass
keeps the frames of its first round for the later ones, up to ``mapper.sharp_frames_kept_mb``.

Rendering poses. A mapping view's pose is its keyframe's pose times ``keyframe_from_view`` (the tracked offset of
the frame it was mapped through, times the bridge's correction; identity with the bridge off), so frontend
corrections and the bridge compose. Any other frame is rendered at ``view @ inverse(view frame) @ frame`` with the
frontend's poses of the frame and of the latest view's frame at or before it (its keyframe's pose times the
tracked offset): the frontend's relative motion, anchored at the refined view.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import logging
from collections.abc import Collection, Mapping

import cv2
import numpy as np
import torch

from tambridge.bridge.blur import ExposurePath, exposure_path, subpose_count
from tambridge.bridge.refinement import refine_render_pose
from tambridge.bridge.view import MappingView
from tambridge.bridge.view_selection import SHARPER_FRAME, Candidate, Selection, select_view, sharpest_candidate, too_blurred
from tambridge.images import sharpness as frame_sharpness
from tambridge.state import attribute_state, restore_attributes
from tambridge.bridge.config import BridgeConfig
from tambridge.frontend.contract import FrontendResult, KeyframeEvent, TrackResult
from tambridge.gaussians.config import ExposureAnchor, MapperConfig
from tambridge.gaussians.mapper import GaussianMap, ViewExposure, ViewImages, backproject, fit_exposure
from tambridge.threads import TORCH_THREADS, compute_threads
from tambridge.geometry import inverse, transform_points
from tambridge.io.prefetch import ReadAhead
from tambridge.io.tum import Frame, RgbdSequence
from tambridge.rolling_shutter import camera_twist_per_s, image_at_frame_time
from tambridge.runlog import RunLog
from tambridge.trajectory import Trajectory

logger = logging.getLogger("tambridge.mapping")

OVERLAP_SAMPLES = 256
"""Pixels of the new view projected into earlier views to measure their overlap."""
def scaled_size(depth_m: np.ndarray, scale: float) -> tuple[int, int]:
    """(width, height) of a frame whose (H, W) depth is ``depth_m``, at ``scale``."""
    height, width = depth_m.shape
    return int(round(width * scale)), int(round(height * scale))


def resize_depth(depth_m: np.ndarray, scale: float) -> torch.Tensor:
    """(H, W) float32 depth in metres at ``scale``, nearest neighbour: blending across an edge invents surfaces."""
    size = scaled_size(depth_m, scale)
    if size != depth_m.shape[::-1]:
        depth_m = cv2.resize(depth_m, size, interpolation=cv2.INTER_NEAREST)
    return torch.from_numpy(np.ascontiguousarray(depth_m))


@dataclasses.dataclass(frozen=True)
class ResizedFrame:
    """A frame resized for the mapper with its colour still as read: rgb8 (H, W, 3) uint8, depth_m (H, W) float32,
    colour_valid (H, W) bool or None (see :class:`ViewImages`); under half the memory of its :class:`ViewImages`."""

    rgb8: np.ndarray
    depth_m: torch.Tensor
    colour_valid: torch.Tensor | None

    @property
    def nbytes(self) -> int:
        return self.rgb8.nbytes + self.depth_m.nbytes + (0 if self.colour_valid is None else self.colour_valid.nbytes)

    def images(self, device: torch.device = torch.device("cpu")) -> ViewImages:
        """The mapper's images (colour as float32 in [0, 1]) on ``device``."""
        return ViewImages(torch.from_numpy(self.rgb8.astype(np.float32) / 255.0), self.depth_m, self.colour_valid).to(device)


def resized_frame(frame: Frame, scale: float, valid_region: tuple[int, int, int, int] | None = None) -> ResizedFrame:
    """A frame at ``scale``: area-averaged colour, depth by :func:`resize_depth`. ``valid_region`` (top, bottom, left,
    right at full resolution, as :attr:`RgbdSequence.valid_region`) marks where the colour has data; None or the
    whole frame: everywhere."""
    height, width = frame.depth_m.shape
    size = scaled_size(frame.depth_m, scale)
    rgb = frame.rgb if size == (width, height) else cv2.resize(frame.rgb, size, interpolation=cv2.INTER_AREA)
    colour_valid = None
    if valid_region is not None and tuple(valid_region) != (0, height, 0, width):
        top, bottom, left, right = valid_region
        # Pixels of the resized image whose whole footprint lies inside the region.
        colour_valid = torch.zeros((size[1], size[0]), dtype=torch.bool)
        colour_valid[int(np.ceil(top * scale)):int(np.floor(bottom * scale)),
                     int(np.ceil(left * scale)):int(np.floor(right * scale))] = True
    return ResizedFrame(rgb, resize_depth(frame.depth_m, scale), colour_valid)


def resize_frame(frame: Frame, scale: float, device: torch.device = torch.device("cpu"),
                 valid_region: tuple[int, int, int, int] | None = None) -> ViewImages:
    """A frame as mapper images at ``scale`` on ``device`` (:func:`resized_frame`)."""
    return resized_frame(frame, scale, valid_region).images(device)


@dataclasses.dataclass(frozen=True)
class FrameBetween:
    """A tracked frame that is not a view, fitted by the sharpening pass: ``world_from_camera`` (4x4) its rendering
    pose (:meth:`MappingStage.rendering_pose`), ``exposure_path`` its motion over the exposure (None: rendered
    sharp), ``view`` the view it is anchored at (whose exposure it is rendered through, where it is)."""

    frame_index: int
    world_from_camera: np.ndarray
    exposure_path: ExposurePath | None
    view: MappingView


class MappingStage:
    """Fusion Bridge + online mapper over one sequence (state across keyframes).

    ``device`` (:func:`tambridge.device.resolve_device` of the run's ``device``) holds the map, the cached images,
    the exposures and every tensor of the bridge; renders come back to the CPU only where numpy needs them.
    """

    def __init__(self, sequence: RgbdSequence, mapper_config: MapperConfig, bridge_config: BridgeConfig, run_log: RunLog,
                 device: torch.device = torch.device("cpu"), seed: int = 0, rolling_shutter_s: float = 0.0) -> None:
        self.sequence = sequence
        self.mapper_config = mapper_config
        self.bridge_config = bridge_config
        self.run_log = run_log
        self.device = device
        self.camera = sequence.camera.scaled(mapper_config.resolution_scale)
        self.map = GaussianMap(mapper_config, device)
        self.views: list[MappingView] = []
        self.keyframe_poses: dict[int, np.ndarray] = {}
        self.selections: collections.Counter = collections.Counter()
        self._cache: collections.OrderedDict[int, ViewImages] = collections.OrderedDict()
        self._rng = np.random.default_rng(seed)
        self._frames_since_keyframe = 0
        # The latest tracked frames, oldest first (sharpness_median_frames of them, at least the window's).
        self._recent: list[Candidate] = []
        # Every tracked frame's sharpness (bridge on), for the frames between the views that the sharpening pass fits.
        self.frame_sharpness: dict[int, float] = {}
        # The colour camera's readout (s) the images are resampled over (0: as recorded), and every tracked frame's
        # camera twist per second (rho, phi), from the frame tracked before it, to resample it with.
        self.rolling_shutter_s = rolling_shutter_s if mapper_config.rolling_shutter_images else 0.0
        self.frame_twists: dict[int, np.ndarray] = {}
        self._last_tracked_timestamp_s: float | None = None
        self._last_tracked_pose = np.eye(4)
        self.blur_exposure_s = blur_exposure_s(bridge_config, sequence)
        # Each view's latest count of renders over its exposure at the mapping resolution (for the metrics).
        self.subposes: dict[int, int] = {}
        logger.info("blur-aware mapping: exposure %.4g s (%s)", self.blur_exposure_s,
                    "off" if not self.blur_exposure_s else "bridge.blur_exposure_s" if bridge_config.blur_exposure_s
                    is not None else "the camera file's exposure_s")

    def threads(self) -> contextlib.AbstractContextManager:
        return compute_threads(TORCH_THREADS, self.mapper_config.kernel_threads)

    # ---- poses ---------------------------------------------------------------------------------------------

    def view_pose(self, view: MappingView) -> np.ndarray:
        """Current 4x4 ``world_from_camera`` of a mapping view: its keyframe's pose times the bridge correction."""
        return self.keyframe_poses[view.keyframe_id] @ view.keyframe_from_view

    def view_poses(self, view: MappingView, camera, depth_m: torch.Tensor) -> np.ndarray:
        """The poses the mapper renders a view at, by ``camera`` (``depth_m`` (H, W) the view's depth at its
        resolution): :meth:`view_pose` along its exposure path (:meth:`poses_over_exposure`)."""
        poses = self.poses_over_exposure(self.view_pose(view), view.exposure_path, camera, depth_m)
        if camera == self.camera:
            self.subposes[view.frame_index] = 1 if poses.ndim == 2 else len(poses)
        return poses

    def poses_over_exposure(self, world_from_camera: np.ndarray, path: ExposurePath | None, camera,
                            depth_m: torch.Tensor) -> np.ndarray:
        """A frame's 4x4 ``world_from_camera``, or (K, 4, 4) along its exposure ``path`` where the image moves
        ``bridge.blur_step_px`` or more over the exposure (:func:`subpose_count`; ``depth_m`` (H, W) at
        ``camera``'s resolution)."""
        # A frame without a path (blur modelling off, the default on real data) needs no look at its depth.
        count = 1 if path is None else subpose_count(path, camera, depth_m.cpu().numpy(), self.bridge_config.blur_step_px,
                                                     self.bridge_config.blur_max_subposes)
        return world_from_camera if count == 1 else world_from_camera @ path.poses(count)

    def exposure_path_of(self, frame_index: int, world_from_frame: np.ndarray,
                         tracked_poses: Mapping[int, np.ndarray] | None = None) -> ExposurePath | None:
        """The exposure path of a frame tracked at ``world_from_frame``, through the tracked frames just before and
        after it (:func:`exposure_path`): those of ``tracked_poses`` (frame index -> 4x4 ``world_from_camera``), else
        those the bridge holds; None with blur modelling off."""
        if tracked_poses is None:
            tracked_poses = {candidate.frame_index: candidate.world_from_camera for candidate in self._recent}
        timestamps = self.sequence.timestamps_s
        neighbours = [(float(timestamps[other]), tracked_poses[other]) for other in (frame_index - 1, frame_index + 1)
                      if other in tracked_poses]
        return exposure_path(np.asarray(world_from_frame, np.float64), float(timestamps[frame_index]), neighbours,
                             self.blur_exposure_s)

    def new_exposure(self) -> ViewExposure | None:
        """The exposure of a new view, pulled to the identity by ``mapper.exposure_prior`` (see
        :class:`ViewExposure`): the first starts at the identity (frozen there with ``mapper.exposure_anchor``
        first_view: it then fixes the map's colour scale), any other from the latest view's; None when
        ``mapper.exposure_compensation`` is off."""
        if not self.mapper_config.exposure_compensation:
            return None
        config = self.mapper_config
        if not self.views:
            return ViewExposure(learning_rate=config.lr_exposure, frozen=config.exposure_anchor is ExposureAnchor.first_view,
                                device=self.device, prior=config.exposure_prior)
        return ViewExposure(self.views[-1].exposure.parameters, config.lr_exposure, prior=config.exposure_prior)

    def anchor_exposures(self) -> None:
        """With ``mapper.exposure_anchor`` median, make the median exposure of the views the identity (per channel,
        log gain and bias), exactly: the map is recoloured into the median view's colours and every exposure rebased
        on it, so that every view renders as before (up to colours leaving [0, 1]) and the map's own colours, those
        a .ply holds, are a typical view's rather than the first view's or wherever the gain-colour ambiguity left
        them. Nothing without exposures."""
        if not self.has_exposures or self.mapper_config.exposure_anchor is not ExposureAnchor.median:
            return
        with torch.no_grad():
            reference = torch.quantile(torch.stack([view.exposure.parameters for view in self.views]), 0.5, dim=0)
            self.map.recolour(ViewExposure(reference, frozen=True))
            for view in self.views:
                view.exposure.rebase(reference)

    @property
    def has_exposures(self) -> bool:
        """Whether there are views and they carry exposures (``mapper.exposure_compensation``)."""
        return bool(self.views) and self.views[0].exposure is not None

    @property
    def fits_frames_as_recorded(self) -> bool:
        """Whether :meth:`finish` runs a sharpening pass against the frames as recorded (no exposure)."""
        return bool(self.mapper_config.sharp_iterations_per_view) and not self.mapper_config.sharp_through_exposures

    def refit_exposures(self) -> int:
        """Fit every view's exposure again to the map as it is now, in closed form (:func:`fit_exposure`): the
        view's render at the mapping resolution against its frame, over the pixels the map covers (silhouette at
        least ``mapper.densify_silhouette``) where the colour has data. After a pass against the frames as recorded
        the map's colours are the frames' own, and exposures fitted before it to other colours would render every
        view, and every frame anchored at it, through a stale transform; so a view the fit cannot explain (too few
        covered pixels, no positive gain) takes the identity, the frames' own colours. Returns how many were
        fitted; nothing without exposures."""
        if not self.has_exposures:
            return 0
        refitted = 0
        for view in self.views:
            images = self.images(view.frame_index)
            rendered = self.map.render(self.camera, self.view_pose(view))
            covered = rendered.silhouette >= self.mapper_config.densify_silhouette
            if images.colour_valid is not None:
                covered &= images.colour_valid
            fitted = fit_exposure(rendered.rgb, images.rgb, covered)
            if fitted is None:
                logger.warning("view %d (frame %d): no exposure fits the map's render (%d covered pixels): "
                               "rendered in the map's own colours", view.keyframe_id, view.frame_index, int(covered.sum()))
            else:
                refitted += 1
            view.exposure.reset(torch.zeros_like(view.exposure.parameters) if fitted is None else fitted)
        return refitted

    @staticmethod
    def exposures(views: list[MappingView]) -> list[ViewExposure | None] | None:
        """The views' exposures for :meth:`GaussianMap.optimise` (None when not compensated)."""
        return None if any(view.exposure is None for view in views) else [view.exposure for view in views]

    def update_keyframe_poses(self, keyframe_poses: dict[int, np.ndarray]) -> None:
        """Take the frontend's latest keyframe poses; the views' Gaussians move with their keyframes."""
        for keyframe_id, pose in keyframe_poses.items():
            if keyframe_id in self.keyframe_poses:
                self.keyframe_poses[keyframe_id] = np.asarray(pose, np.float64)
        for view in self.views:
            self.map.set_anchor_pose(view.keyframe_id, self.view_pose(view))

    # ---- images --------------------------------------------------------------------------------------------

    def images(self, frame_index: int, frame: Frame | None = None) -> ViewImages:
        """A view's images at the mapping resolution, from the cache or read again from the sequence."""
        if frame_index in self._cache:
            self._cache.move_to_end(frame_index)
            return self._cache[frame_index]
        images = resize_frame(self.at_frame_time(frame if frame is not None else self.sequence[frame_index]),
                              self.mapper_config.resolution_scale, self.device, self.sequence.valid_region)
        self._cache[frame_index] = images
        while len(self._cache) > self.mapper_config.window_size + 1:
            self._cache.popitem(last=False)
        return images

    def at_frame_time(self, frame: Frame) -> Frame:
        """The frame with its colour resampled to a global shutter at its time (:func:`image_at_frame_time`) by its
        tracked motion, with a rolling-shutter camera; as recorded otherwise, or where its motion is unknown."""
        twist = self.frame_twists.get(frame.index)
        if not self.rolling_shutter_s or twist is None:
            return frame
        return dataclasses.replace(frame, rgb=image_at_frame_time(frame.rgb, frame.depth_m, self.sequence.camera, twist,
                                                                  self.rolling_shutter_s))

    # ---- online --------------------------------------------------------------------------------------------

    def on_tracked(self, result: TrackResult, frame: Frame, sharpness: float | None = None) -> None:
        """Note a tracked frame (before its keyframe event, if it is a keyframe): its motion from the frame tracked
        before it (for :meth:`at_frame_time`), and as a candidate view of the next keyframe; ``sharpness``: its
        :func:`tambridge.images.sharpness` where the read-ahead scored it."""
        if not result.tracked:
            return
        world_from_camera = np.asarray(result.world_from_camera, np.float64)
        if self.rolling_shutter_s and self._last_tracked_timestamp_s is not None:
            interval_s = frame.timestamp_s - self._last_tracked_timestamp_s
            if interval_s > 0:
                self.frame_twists[frame.index] = camera_twist_per_s(inverse(world_from_camera) @ self._last_tracked_pose,
                                                                    interval_s)
        self._last_tracked_timestamp_s, self._last_tracked_pose = frame.timestamp_s, world_from_camera
        bridge = self.bridge_config
        if not bridge.enabled:
            return
        # The per-frame share of the bridge's cost (a score where the read-ahead gave none).
        score = frame_sharpness(frame.rgb) if sharpness is None else sharpness
        self.frame_sharpness[frame.index] = score
        self._recent.append(Candidate(frame.index, np.asarray(result.world_from_camera, np.float64), score,
                                      result.inlier_count))
        del self._recent[: max(0, len(self._recent) - max(bridge.sharpness_median_frames, bridge.sharpest_window + 1))]
        # The view of the frame before, mapped at constant velocity (or without a path: the first frame), now has
        # its path through both neighbours.
        for view in self.views[-2:]:
            if view.frame_index == frame.index - 1 and self.blur_exposure_s:
                view.exposure_path = self.exposure_path_of(view.frame_index, self.tracked_pose(view))

    def view_frame(self, event: KeyframeEvent, selection: Selection, frame: Frame) -> tuple[Candidate, Selection]:
        """The frame to map for a keyframe eq. 3 selected, and its final selection: the sharpest candidate of its
        window within eq. 3 (:func:`sharpest_candidate`), or ``TOO_BLURRED`` where that is far below the recent
        median and the map already explains the keyframe (:meth:`uncovered`); the first keyframe and an uncovered
        one eq. 3 rejected are mapped as they are."""
        bridge = self.bridge_config
        earlier = [candidate for candidate in self._recent if candidate.frame_index < event.frame_index]
        own = [candidate.sharpness for candidate in self._recent if candidate.frame_index == event.frame_index]
        keyframe = Candidate(event.frame_index, np.asarray(event.world_from_camera, np.float64),
                             own[0] if own else frame_sharpness(frame.rgb), event.shared_with_previous)
        if selection in (Selection.FIRST, Selection.UNCOVERED):
            return keyframe, selection
        # Frames after the latest view only: an earlier one is already the map's.
        latest_view = max((view.frame_index for view in self.views), default=-1)
        window = [candidate for candidate in earlier[len(earlier) - bridge.sharpest_window:]
                  if candidate.frame_index > latest_view] if bridge.sharpest_window else []
        chosen = sharpest_candidate(keyframe, window, event.previous_total, bridge.alpha, bridge.beta,
                                    bridge.sharper_by)
        recent = [candidate.sharpness for candidate in earlier]
        # A blurred view is still better than none where the map lacks what the keyframe sees.
        if too_blurred(chosen.sharpness, recent, bridge.blur_reject_ratio, bridge.sharpest_window + 1) and \
                not self.uncovered(frame, self.rendering_pose(event.frame_index, event.world_from_camera)):
            return chosen, Selection.TOO_BLURRED
        return chosen, selection

    def on_keyframe(self, event: KeyframeEvent, frame: Frame, keyframe_poses: dict[int, np.ndarray]) -> None:
        """One keyframe from the frontend: select, refine, map. ``keyframe_poses`` are the frontend's current ones."""
        with self.threads():
            self._on_keyframe(event, frame, keyframe_poses)

    def _on_keyframe(self, event: KeyframeEvent, frame: Frame, keyframe_poses: dict[int, np.ndarray]) -> None:
        bridge = self.bridge_config
        self._frames_since_keyframe = 0
        selection = select_view(event, not self.keyframe_poses, bridge.enabled, bridge.alpha, bridge.beta)
        self.keyframe_poses[event.keyframe_id] = np.asarray(event.world_from_camera, np.float64)
        self.update_keyframe_poses(keyframe_poses)
        if not selection.selected and self.uncovered(frame, self.rendering_pose(event.frame_index, event.world_from_camera)):
            selection = Selection.UNCOVERED
        chosen = Candidate(event.frame_index, np.asarray(event.world_from_camera, np.float64), float("nan"),
                           event.shared_with_previous)
        if selection.selected and bridge.enabled:
            with self.run_log.stage("bridge"):
                chosen, selection = self.view_frame(event, selection, frame)
        self.selections[selection.name] += 1
        if not selection.selected:
            return
        replaced = chosen.frame_index != event.frame_index
        if replaced:
            self.selections[SHARPER_FRAME] += 1
            # Read again (once per view, the bridge's cost): the window keeps no images.
            with self.run_log.stage("bridge"):
                images = self.images(chosen.frame_index)
        else:
            images = self.images(event.frame_index, frame)
        # The frame's pose relative to its keyframe as tracked (the keyframe pose as inserted, before local BA).
        keyframe_from_frame = (inverse(np.asarray(event.world_from_camera, np.float64)) @ chosen.world_from_camera
                               if replaced else np.eye(4))
        frame_pose = self.keyframe_poses[event.keyframe_id] @ keyframe_from_frame
        exposure = self.new_exposure()
        refinement = None
        keyframe_from_view = keyframe_from_frame
        if bridge.enabled and bridge.refine_poses and len(self.map):
            with self.run_log.stage("bridge"):
                # A replacing frame has no keypoints of its own: its refinement uses the rendering terms only.
                points = np.zeros((0, 3)) if replaced else event.points_world_m
                keypoints = np.zeros((0, 2)) if replaced else \
                    (np.asarray(event.keypoints_px, np.float64).reshape(-1, 2) + 0.5) * self.mapper_config.resolution_scale - 0.5
                # Only the Gaussians in view at the frontend pose: the refinement moves the pose by centimetres.
                in_view = self.map.visible_rows(self.camera, frame_pose)
                with torch.no_grad():
                    gaussians = self.map.gaussians(rows=in_view)
                # The colour term compares map colours: the frame's, through the exposure it starts from.
                observed_rgb = images.rgb if exposure is None else exposure.invert(images.rgb)
                refinement = refine_render_pose(gaussians, self.camera, frame_pose, observed_rgb, images.depth_m, points,
                                                keypoints, bridge, backend=self.mapper_config.backend,
                                                colour_weight=self.colour_weight(chosen))
                keyframe_from_view = inverse(self.keyframe_poses[event.keyframe_id]) @ refinement.world_from_camera
                logger.info("frame %d: reprojection %.2f px, joint loss %.4f -> %.4f, pose moved %.2f mm%s",
                             chosen.frame_index, refinement.reprojection_px, refinement.loss_initial, refinement.loss_final,
                             1e3 * np.linalg.norm(refinement.world_from_camera[:3, 3] - frame_pose[:3, 3]),
                             " (skipped)" if refinement.skipped else "")
        view = MappingView(event.keyframe_id, chosen.frame_index, keyframe_from_view, selection, refinement, exposure,
                           keyframe_from_frame=keyframe_from_frame, sharpness=chosen.sharpness,
                           exposure_path=self.exposure_path_of(chosen.frame_index, chosen.world_from_camera))
        with self.run_log.stage("mapping"):
            self.map_view(view, images)

    def tracked_pose(self, view: MappingView) -> np.ndarray:
        """4x4 tracked ``world_from_camera`` of a view's frame among the bridge's recent frames (its keyframe's
        pose times the tracked offset where it has dropped out of them)."""
        tracked = [candidate.world_from_camera for candidate in self._recent if candidate.frame_index == view.frame_index]
        return tracked[0] if tracked else self.keyframe_poses[view.keyframe_id] @ view.keyframe_from_frame

    def colour_weight(self, chosen: Candidate) -> float:
        """Scale of the refinement's colour term for a view: its sharpness over the recent median, at most 1."""
        recent = [candidate.sharpness for candidate in self._recent]
        if not self.bridge_config.sharpness_weighted_colour or not recent:
            return 1.0
        median = float(np.median(recent))
        return 1.0 if median <= 0 else float(min(1.0, chosen.sharpness / median))

    def needs_view(self, result: TrackResult, frame: Frame) -> bool:
        """Whether a tracked frame that is not a keyframe should become a mapping view because the map lacks too
        much of it (:meth:`uncovered`); checked every ``mapper.coverage_check_every``-th frame after a keyframe."""
        if result.is_keyframe or not result.tracked or not self.views or not self.mapper_config.coverage_unexplained:
            return False
        self._frames_since_keyframe += 1
        if self._frames_since_keyframe % max(1, self.mapper_config.coverage_check_every):
            return False
        with self.threads():
            return self.uncovered(frame, self.rendering_pose(frame.index, result.world_from_camera))

    def uncovered(self, frame: Frame, world_from_camera: np.ndarray) -> bool:
        """Whether the map, rendered at ``world_from_camera``, leaves ``mapper.coverage_unexplained`` more of the
        frame's valid depth pixels unexplained than of its anchor view's (always False with the rule off or no view).
        The anchor view's share is what the map cannot explain even where it was made (depth noise and holes, a
        map of one view)."""
        threshold = self.mapper_config.coverage_unexplained
        if not threshold or not self.views:
            return False
        with self.run_log.stage("coverage"):
            # Depth only: the check never looks at colour, and it runs every coverage_check_every-th frame.
            depth_m = resize_depth(frame.depth_m, self.mapper_config.resolution_scale).to(self.device)
            fraction = self.map.unexplained_fraction(self.camera, world_from_camera, depth_m)
        floor = self.anchor_view(frame.index).unexplained
        logger.debug("frame %d: %.1f %% of its depth unexplained by the map (%.1f %% at its view)", frame.index,
                     100 * fraction, 100 * floor)
        return fraction - floor > threshold

    def map_view(self, view: MappingView, images: ViewImages) -> None:
        """Add a view to the map: densify, optimise over it and its overlapping window, prune."""
        world_from_camera = self.view_pose(view)
        self.map.set_anchor_pose(view.keyframe_id, world_from_camera)
        rendered = self.map.render(self.camera, world_from_camera) if len(self.map) else None
        added = self.map.densify(view.keyframe_id, self.camera, images, rendered, view.exposure)
        added += self.map.densify_unmeasured(view.keyframe_id, self.camera, images, rendered, view.exposure,
                                             self.mapper_config.densify_unmeasured)
        window = self.overlapping_views(world_from_camera, images)
        self.views.append(view)
        views = [self.posed_images(v, self.images(v.frame_index) if v is not view else images) for v in [view] + window]
        # Every other step on the new view, the others cycle through the earlier overlapping ones.
        steps = self.mapper_config.iterations * self.steps_factor(view)
        schedule = [0 if k % 2 == 0 or not window else 1 + (k // 2) % len(window) for k in range(steps)]
        losses = self.map.optimise(self.camera, views, schedule, self.exposures([view] + window))
        self.anchor_exposures()
        removed = self.map.prune(self.camera, world_from_camera)
        if self.mapper_config.coverage_unexplained:
            view.unexplained = self.map.unexplained_fraction(self.camera, world_from_camera, images.depth_m)
        own = [loss for loss, index in zip(losses, schedule) if index == 0] or [float("nan")]
        logger.info("view %d (frame %d, %s): +%d -%d Gaussians -> %d, window %s, its loss %.4f -> %.4f, %d render(s) "
                    "over its exposure", len(self.views) - 1, view.frame_index, view.selection.value, added, removed,
                    len(self.map), [v.frame_index for v in window], own[0], own[-1], self.subposes.get(view.frame_index, 1))

    def steps_factor(self, view: MappingView) -> int:
        """``bridge.blur_steps_factor`` for a view whose latest :meth:`view_poses` rendered it over its exposure
        (more than one sub-pose), else 1."""
        return self.bridge_config.blur_steps_factor if self.subposes.get(view.frame_index, 1) > 1 else 1

    def posed_images(self, view: MappingView, images: ViewImages, camera=None) -> tuple[np.ndarray, ViewImages]:
        """``(poses, images)`` of a view for :meth:`GaussianMap.optimise`: :meth:`view_poses` by ``camera`` (None:
        the mapping camera) at ``images``' resolution."""
        return self.view_poses(view, self.camera if camera is None else camera, images.depth_m), images

    def overlapping_views(self, world_from_camera: np.ndarray, images: ViewImages) -> list[MappingView]:
        """The ``window_size - 1`` earlier views that see the most of this view's points (at least one point)."""
        if not self.views or self.mapper_config.window_size <= 1:
            return []
        points_camera = backproject(images.depth_m, self.camera, images.depth_m > 0).cpu().numpy().astype(np.float64)
        if len(points_camera) == 0:
            return []
        sample = points_camera[self._rng.choice(len(points_camera), min(OVERLAP_SAMPLES, len(points_camera)), replace=False)]
        points_world = transform_points(world_from_camera, sample)
        overlaps = []
        for view in self.views:
            points_view = transform_points(inverse(self.view_pose(view)), points_world)
            pixels = self.camera.project(points_view, np.maximum(points_view[:, 2], 1e-6))
            inside = (points_view[:, 2] > 0) & self.camera.in_image(pixels)
            overlaps.append(float(inside.mean()))
        order = np.argsort(overlaps)[::-1][: self.mapper_config.window_size - 1]
        return [self.views[i] for i in order if overlaps[i] > 0]

    # ---- after the frontend ----------------------------------------------------------------------------------

    def finish(self, keyframe_poses: dict[int, np.ndarray], tracking: FrontendResult | None = None,
               held_out: Collection[int] = ()) -> None:
        """Move every view to the final keyframe poses, run ``final_iterations_per_view`` more steps on each view
        (in random order; times :meth:`steps_factor`), then the sharpening pass (:meth:`sharpen`) over the views and
        the tracked frames between them that ``tracking`` (the frontend's final result; None: views only) gives,
        never a frame of ``held_out`` (the evaluation's novel views), and prune. The map's colours, those splats.ply
        holds, are then the frames' own after a pass against the frames as recorded, every exposure refitted to them
        (:meth:`refit_exposures`); else those :meth:`anchor_exposures` gives."""
        with self.run_log.stage("final_refinement"), self.threads():
            self.update_keyframe_poses(keyframe_poses)
            for chunk in self.view_chunks():
                views = [self.posed_images(v, self.images(v.frame_index)) for v in chunk]
                steps = [self.mapper_config.final_iterations_per_view * self.steps_factor(v) for v in chunk]
                self.map.optimise(self.camera, views, round_robin(steps), self.exposures(chunk))
        frames_between = [] if tracking is None or not self.mapper_config.sharp_iterations_per_view else \
            self.frames_between(tracking, held_out)
        self.sharpen_prune_and_set_colours(frames_between)

    def sharpen_prune_and_set_colours(self, frames_between: list[FrameBetween]) -> None:
        """The end of :meth:`finish`, after the final refinement: the sharpening pass over the views and
        ``frames_between`` (where ``mapper.sharp_iterations_per_view``), the prune, then the map's colours."""
        if self.mapper_config.sharp_iterations_per_view:
            with self.run_log.stage("sharpening"), self.threads():
                self.sharpen(frames_between)
        if self.views:
            with self.run_log.stage("final_refinement"):
                removed = self.final_prune()
            logger.info("final refinement: %d steps per view over %d views, %d Gaussians pruned -> %d",
                        self.mapper_config.final_iterations_per_view, len(self.views), removed, len(self.map))
        if not self.fits_frames_as_recorded:
            self.anchor_exposures()
        elif self.has_exposures:
            with self.run_log.stage("sharpening"), self.threads():
                refitted = self.refit_exposures()
            logger.info("exposures refitted to the map as recorded: %d of %d views", refitted, len(self.views))

    def final_prune(self) -> int:
        """The prune that ends :meth:`finish`, seen from the last view; returns how many Gaussians it removed."""
        return self.map.prune(self.camera, self.view_pose(self.views[-1]))

    def view_chunks(self) -> list[list[MappingView]]:
        """The views in random order, a window's worth at a time (bounded memory), for the passes after tracking."""
        return shuffled_chunks(self.views, self.mapper_config.window_size, self._rng)

    def frames_between(self, tracking: FrontendResult, held_out: Collection[int]) -> list[FrameBetween]:
        """The tracked frames the sharpening pass fits besides the views: ``mapper.sharp_frames_between`` between
        each view's frame and the next one's (after the last view: up to the sequence's end), one from each equal
        share of the tracked frames there that are not in ``held_out`` nor tracked by their depth alone
        (:func:`frames_between_views`): with the bridge on the share's sharpest, else its middle; each at its
        rendering pose, rendered over its exposure where blur modelling is on."""
        if not self.views or not self.mapper_config.sharp_frames_between:
            return []
        usable = np.asarray(tracking.tracked, bool).copy()
        if tracking.tracked_by_depth is not None:
            # Their colour is what the tracker could not use (a covered lens, no texture, heavy blur).
            usable &= ~tracking.tracked_by_depth
        usable[[index for index in held_out if 0 <= index < len(usable)]] = False
        sharpness = None
        if self.bridge_config.enabled:
            sharpness = np.full(len(usable), np.nan)
            scored = [index for index in self.frame_sharpness if index < len(usable)]
            sharpness[scored] = [self.frame_sharpness[index] for index in scored]
        poses = tracking.trajectory.world_from_camera
        frames = []
        for index in frames_between_views([view.frame_index for view in self.views], usable,
                                          self.mapper_config.sharp_frames_between, sharpness):
            neighbours = {other: poses[other] for other in (index - 1, index + 1)
                          if 0 <= other < len(usable) and tracking.tracked[other]}
            frames.append(FrameBetween(index, self.rendering_pose(index, poses[index]),
                                       self.exposure_path_of(index, poses[index], neighbours), self.anchor_view(index)))
        return frames

    def sharpen(self, frames_between: list[FrameBetween] = ()) -> None:
        """The sharpening pass: every view's frame read again at ``mapper.sharp_resolution_scale`` and every one of
        ``frames_between`` at ``mapper.sharp_between_resolution_scale`` (each at least ``mapper.resolution_scale``),
        Gaussians added where a view's colour error is worst (``sharp_densify_*``, first round), then
        ``sharp_iterations_per_view`` rounds of one Adam step on each view and frame, a chunk of views or of frames
        at a time so that only a window's frames are held, in a new order each round, at learning rates falling
        from ``sharp_lr_scale_start`` to ``sharp_lr_scale_end`` times the online ones, with the squared colour error
        weighed by ``sharp_w_colour_squared`` beside the online loss's terms; through the views' exposures
        (a frame between: its anchor view's), or against the frames as recorded (``sharp_through_exposures``)."""
        config = self.mapper_config
        # Never coarser than the online mapping: a map fitted at a finer resolution would only be blurred.
        scales = {MappingView: max(config.sharp_resolution_scale, config.resolution_scale),
                  FrameBetween: max(config.sharp_between_resolution_scale, config.resolution_scale)}
        cameras = {kind: self.sequence.camera.scaled(scale) for kind, scale in scales.items()}
        added = 0
        start, end = config.sharp_lr_scale_start, config.sharp_lr_scale_end

        # Frames of the first round are kept for the later ones while they fit in sharp_frames_kept_mb; the rest
        # are read again (decoding, colour registration and the rolling shutter's resampling take CPU the steps need).
        # A pass of one round keeps nothing.
        kept: dict[tuple[type, int], ResizedFrame] = {}
        kept_bytes_left = config.sharp_frames_kept_mb * 2**20 if config.sharp_iterations_per_view > 1 else 0

        def read(item: MappingView | FrameBetween) -> ResizedFrame:
            key = (type(item), item.frame_index)
            if key in kept:
                return kept[key]
            return resized_frame(self.at_frame_time(self.sequence[item.frame_index]), scales[type(item)],
                                 self.sequence.valid_region)

        for round_index in range(config.sharp_iterations_per_view):
            chunks = self.view_chunks()
            if frames_between:
                chunks += shuffled_chunks(list(frames_between), config.window_size, self._rng)
                chunks = [chunks[index] for index in self._rng.permutation(len(chunks))]
            # Frames not kept are read a few ahead in a worker thread (decoding and colour registration overlap the
            # steps): holding every view at this resolution would not be bounded.
            with ReadAhead([item for chunk in chunks for item in chunk], read) as reading:
                frames_read = iter(reading)
                for chunk_index, chunk in enumerate(chunks):
                    # Linear in the pass's progress, chunk by chunk, from sharp_lr_scale_start towards sharp_lr_scale_end.
                    progress = (round_index + chunk_index / len(chunks)) / config.sharp_iterations_per_view
                    learning_rate_scale = start + (end - start) * progress
                    kind = type(chunk[0])
                    camera = cameras[kind]
                    posed, exposure_views = [], []
                    for item in chunk:
                        resized = next(frames_read)
                        if round_index == 0 and resized.nbytes <= kept_bytes_left:
                            kept[(type(item), item.frame_index)] = resized
                            kept_bytes_left -= resized.nbytes
                        images = resized.images(self.device)
                        if kind is FrameBetween:
                            poses = self.poses_over_exposure(item.world_from_camera, item.exposure_path, camera, images.depth_m)
                            exposure_views.append(item.view)
                        else:
                            poses = self.view_poses(item, camera, images.depth_m)
                            exposure_views.append(item)
                            if round_index == 0:
                                added += self.map.densify_colour_error(
                                    item.keyframe_id, camera, images, item.exposure if config.sharp_through_exposures else None,
                                    config.sharp_densify_error, config.sharp_densify_fraction, poses if poses.ndim == 3 else None)
                        posed.append((poses, images))
                    self.map.optimise(camera, posed, list(range(len(chunk))),
                                      self.exposures(exposure_views) if config.sharp_through_exposures else None,
                                      learning_rate_scale, config.sharp_w_colour_squared)
        logger.info("sharpening at %dx%d: %d steps per view over %d views and %d frames between them (at %dx%d), "
                    "+%d Gaussians -> %d; %d frames kept for the later rounds (%.0f MB)", cameras[MappingView].width,
                    cameras[MappingView].height, config.sharp_iterations_per_view, len(self.views), len(frames_between),
                    cameras[FrameBetween].width, cameras[FrameBetween].height, added, len(self.map), len(kept),
                    sum(resized.nbytes for resized in kept.values()) / 2**20)

    def rendering_poses(self, trajectory: Trajectory) -> np.ndarray:
        """(N, 4, 4) rendering pose of every frame of the frontend's ``trajectory`` (see the module doc).

        ``trajectory`` must be the frontend's final per-frame trajectory, the same poses as the final keyframe poses.
        """
        return np.stack([self.rendering_pose(index, pose) for index, pose in enumerate(trajectory.world_from_camera)])

    def rendering_pose(self, frame_index: int, world_from_camera: np.ndarray) -> np.ndarray:
        """4x4 rendering pose of a frame at the frontend's ``world_from_camera``: anchored at its :meth:`anchor_view`."""
        world_from_camera = np.asarray(world_from_camera, np.float64)
        if not self.views:
            return world_from_camera.copy()
        view = self.anchor_view(frame_index)
        view_frame_pose = self.keyframe_poses[view.keyframe_id] @ view.keyframe_from_frame
        return self.view_pose(view) @ inverse(view_frame_pose) @ world_from_camera

    def anchor_view(self, frame_index: int) -> MappingView:
        """The mapping view a frame is rendered from: the latest at or before it (the first for earlier frames)."""
        earlier = [view for view in self.views if view.frame_index <= frame_index]
        return max(earlier, key=lambda view: view.frame_index) if earlier else min(self.views, key=lambda view: view.frame_index)

    def state_dict(self) -> dict:
        """What a resumed run needs: the Gaussian map (:meth:`GaussianMap.state_dict`), the views, keyframe poses,
        selection counts, the image cache and the random generator; not the sequence, configs or run log. Its
        tensors are on the CPU (a checkpoint written on a GPU loads anywhere)."""
        state = attribute_state(self, ("sequence", "mapper_config", "bridge_config", "run_log", "camera", "map", "device"))
        state["map"] = self.map.state_dict()
        return _stage_tensors_to(state, torch.device("cpu"))

    def load_state_dict(self, state: dict) -> None:
        """Continue from :meth:`state_dict` (on a stage built with the same sequence and configs); tensors go to
        this stage's device."""
        state = dict(state)
        self.map.load_state_dict(state.pop("map"))
        restore_attributes(self, _stage_tensors_to(state, self.device))


def frames_between_views(view_frames: list[int], usable: np.ndarray, count: int,
                         sharpness: np.ndarray | None = None) -> list[int]:
    """Up to ``count`` frame indices strictly between each pair of consecutive ``view_frames`` (any order; after the
    last one: up to ``len(usable)``) among those where ``usable`` (N,) bool holds, one from each of ``count`` equal
    shares of the usable frames there (all of them where there are ``count`` or fewer): the share's middle frame, or
    with ``sharpness`` (N,), each frame's :func:`tambridge.images.sharpness` (NaN: not scored), its sharpest scored
    frame (the middle where none is scored)."""
    bounds = sorted(set(view_frames)) + [len(usable)]
    chosen = []
    for start, stop in zip(bounds, bounds[1:]):
        candidates = [index for index in range(start + 1, stop) if usable[index]]
        if len(candidates) <= count:
            chosen += candidates
            continue
        for share in range(count):
            members = candidates[share * len(candidates) // count : (share + 1) * len(candidates) // count]
            scored = [] if sharpness is None else [index for index in members if np.isfinite(sharpness[index])]
            chosen.append(max(scored, key=lambda index: sharpness[index]) if scored
                          else candidates[int((share + 0.5) * len(candidates) / count)])
    return chosen


def shuffled_chunks(items: list, chunk_size: int, rng: np.random.Generator) -> list[list]:
    """``items`` in a random order drawn from ``rng``, cut into lists of ``chunk_size`` (at least 1), the last shorter:
    the order of the passes over views after tracking, a new one each pass or round."""
    order = [items[i] for i in rng.permutation(len(items))]
    size = max(1, chunk_size)
    return [order[start : start + size] for start in range(0, len(order), size)]


def round_robin(steps: list[int]) -> list[int]:
    """A schedule of view indices in which view ``i`` appears ``steps[i]`` times: rounds over the views that have
    steps left, in order (equal counts: ``list(range(n)) * steps[0]``)."""
    return [index for round_ in range(max(steps, default=0)) for index, count in enumerate(steps) if round_ < count]


def blur_exposure_s(bridge: BridgeConfig, sequence: RgbdSequence) -> float:
    """The exposure time (s) blur-aware mapping integrates over: ``bridge.blur_exposure_s``, else the sequence's
    camera file's ``exposure_s``, else 0 (off); 0 with the bridge off."""
    if not bridge.enabled:
        return 0.0
    if bridge.blur_exposure_s is not None:
        return bridge.blur_exposure_s
    return sequence.sensor.exposure_s or 0.0


def _stage_tensors_to(state: dict, device: torch.device) -> dict:
    """``state`` (of :meth:`MappingStage.state_dict`, the map's part aside) with the cached images and the views'
    exposures on ``device``; the stage's own objects are not changed (moved ones are copies)."""
    state = dict(state)
    state["_cache"] = collections.OrderedDict(
        (index, images.to(device)) for index, images in state["_cache"].items())
    views = []
    for view in state["views"]:
        exposure = None if view.exposure is None else view.exposure.to(device)
        views.append(view if exposure is view.exposure else dataclasses.replace(view, exposure=exposure))
    state["views"] = views
    return state
