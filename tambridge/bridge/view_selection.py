"""Which frames become mapping views (paper Sec. 3.3, eq. 3, and the blur-aware choice of the frame).

Keyframe i is selected when ``beta <= M(i-1, i) < alpha * T(i-1, i)``: it shares enough map points with the
previous keyframe for the reprojection term of the pose refinement (lower bound) but not so many that it adds
nothing new to the map (upper bound). ``M`` is the number of map points keyframe i shares with keyframe i-1,
``T`` the number of map points matched in keyframe i-1.

Eq. 3 looks at the sparse map only. A keyframe it rejects is still taken when the Gaussian map leaves too much of
it unexplained (``Selection.UNCOVERED``, decided by the mapping stage): moving back from a scene, a camera keeps
tracking the same points (``M`` stays near ``T``) while new surfaces enter the image at its borders.

Eq. 3 does not see blur: a blurred keyframe still shares hundreds of points. So the bridge maps, in place of a
selected keyframe, the sharpest tracked frame of the few before it (:func:`sharpest_candidate`) that still passes
eq. 3's bounds, and skips a view whose sharpness is far below the recent median (:func:`too_blurred`). The
frames after a keyframe are not tracked yet when the bridge maps it, so the window runs back from the keyframe.
"""

from __future__ import annotations

import dataclasses
import enum

import numpy as np

from tambridge.frontend.contract import KeyframeEvent


class Selection(enum.Enum):
    """Why a keyframe was or was not taken as a mapping view."""

    FIRST = "first keyframe"
    SELECTED = "beta <= M < alpha * T"
    TOO_FEW_SHARED = "M < beta"
    TOO_SIMILAR = "M >= alpha * T"
    NO_SPARSE_MAP = "frontend has no sparse map (T = 0): every keyframe is a view"
    BRIDGE_OFF = "bridge disabled: every keyframe is a view"
    UNCOVERED = "rejected by eq. 3, but the Gaussian map leaves too much of it unexplained"
    TOO_BLURRED = "selected, but even its sharpest candidate frame is far below the recent median sharpness"

    @property
    def selected(self) -> bool:
        return self in (Selection.FIRST, Selection.SELECTED, Selection.NO_SPARSE_MAP, Selection.BRIDGE_OFF, Selection.UNCOVERED)


SHARPER_FRAME = "SHARPER_FRAME"
"""Key of the selection counts (beside the :class:`Selection` names) of the selected keyframes that were mapped
through a sharper frame of their window."""


@dataclasses.dataclass
class Candidate:
    """A tracked frame that may be mapped in place of the next keyframe: its index, tracked 4x4
    ``world_from_camera``, :func:`tambridge.images.sharpness` and the number of map points it tracked."""

    frame_index: int
    world_from_camera: np.ndarray
    sharpness: float
    tracked_points: int


def covisibility_selection(shared_with_previous: int, previous_total: int, alpha: float, beta: int) -> Selection:
    """Eq. 3 on the match counts ``M(i-1, i)`` and ``T(i-1, i)`` of a keyframe that is not the first.

    A frontend without a sparse map (the Open3D ones: ``T = 0``) gives eq. 3 nothing to count; then every
    keyframe is selected, because those frontends already space their keyframes by motion, which is the
    diversity that the upper bound asks for, and the refinement runs on the rendering terms alone.
    """
    if previous_total == 0:
        return Selection.NO_SPARSE_MAP
    if shared_with_previous < beta:
        return Selection.TOO_FEW_SHARED
    if shared_with_previous >= alpha * previous_total:
        return Selection.TOO_SIMILAR
    return Selection.SELECTED


def select_view(event: KeyframeEvent, is_first: bool, enabled: bool, alpha: float, beta: int) -> Selection:
    """Selection of one keyframe event: the first keyframe always (the map starts from it), all with the bridge off."""
    if is_first:
        return Selection.FIRST
    if not enabled:
        return Selection.BRIDGE_OFF
    return covisibility_selection(event.shared_with_previous, event.previous_total, alpha, beta)


def sharpest_candidate(keyframe: Candidate, candidates: list[Candidate], previous_total: int, alpha: float,
                       beta: int, margin: float = 1.0) -> Candidate:
    """The sharpest of the ``candidates`` that pass eq. 3's bounds against the previous keyframe's
    ``previous_total`` (``T``) where it is at least ``margin`` times as sharp as ``keyframe`` (which passed eq. 3),
    else the keyframe: among frames about as sharp, the keyframe sees the most that is new.

    A candidate's ``M`` is the number of map points it tracked: it is not a keyframe, so the frontend does not
    count the points it shares with the previous keyframe, and the points it tracked bound them from above (the
    upper bound is checked strictly, the lower one is met by at least as many tracked points).
    """
    eligible = [candidate for candidate in candidates
                if covisibility_selection(candidate.tracked_points, previous_total, alpha, beta)
                in (Selection.SELECTED, Selection.NO_SPARSE_MAP)]
    sharpest = max(eligible, key=lambda candidate: candidate.sharpness, default=keyframe)
    return sharpest if sharpest.sharpness > margin * keyframe.sharpness else keyframe


def too_blurred(sharpness: float, recent_sharpness: list[float], ratio: float, min_recent: int) -> bool:
    """Whether a view's ``sharpness`` is below ``ratio`` times the median of ``recent_sharpness`` (the tracked
    frames before it); never with ``ratio`` 0 or fewer than ``min_recent`` recent frames to take a median of."""
    if ratio <= 0 or len(recent_sharpness) < max(1, min_recent):
        return False
    return sharpness < ratio * float(np.median(recent_sharpness))
