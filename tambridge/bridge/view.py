"""The bridge-to-mapper contract: a keyframe taken as a mapping view, with the bridge's pose correction."""

from __future__ import annotations

import dataclasses

import numpy as np

from tambridge.bridge.blur import ExposurePath
from tambridge.bridge.refinement import RefinementResult
from tambridge.bridge.view_selection import Selection
from tambridge.gaussians.mapper import ViewExposure


@dataclasses.dataclass
class MappingView:
    """A keyframe taken as a mapping view, mapped through frame ``frame_index`` (the keyframe's own frame, or a
    sharper tracked frame before it). ``keyframe_from_view`` (4x4) places the view at its keyframe: the frame's
    tracked offset ``keyframe_from_frame`` (identity for the keyframe's own frame) times the bridge's pose
    correction; ``exposure`` its colour transform (None: the mapper does not compensate exposure); ``unexplained``
    the share of its depth pixels the map left unexplained once it was mapped
    (:meth:`GaussianMap.unexplained_fraction`); ``sharpness`` the frame's :func:`tambridge.images.sharpness`;
    ``exposure_path`` the camera's motion over the frame's exposure (None: rendered sharp), see
    :mod:`tambridge.bridge.blur`."""

    keyframe_id: int
    frame_index: int
    keyframe_from_view: np.ndarray
    selection: Selection
    refinement: RefinementResult | None
    exposure: ViewExposure | None = None
    unexplained: float = 0.0
    keyframe_from_frame: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    sharpness: float = float("nan")
    exposure_path: ExposurePath | None = None
