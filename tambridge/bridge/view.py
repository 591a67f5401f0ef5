"""The bridge-to-mapper contract: a keyframe taken as a mapping view, with the bridge's pose correction."""

from __future__ import annotations

import dataclasses

import numpy as np

from tambridge.bridge.refinement import RefinementResult
from tambridge.bridge.view_selection import Selection
from tambridge.gaussians.mapper import ViewExposure


@dataclasses.dataclass
class MappingView:
    """A keyframe taken as a mapping view. ``keyframe_from_view`` (4x4) is the bridge's pose correction;
    ``exposure`` its colour transform (None: the mapper does not compensate exposure); ``unexplained`` the share of
    its depth pixels the map left unexplained once it was mapped (:meth:`GaussianMap.unexplained_fraction`)."""

    keyframe_id: int
    frame_index: int
    keyframe_from_view: np.ndarray
    selection: Selection
    refinement: RefinementResult | None
    exposure: ViewExposure | None = None
    unexplained: float = 0.0
