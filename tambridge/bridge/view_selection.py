"""Which keyframes become mapping views (paper Sec. 3.3, eq. 3).

Keyframe i is selected when ``beta <= M(i-1, i) < alpha * T(i-1, i)``: it shares enough map points with the
previous keyframe for the reprojection term of the pose refinement (lower bound) but not so many that it adds
nothing new to the map (upper bound). ``M`` is the number of map points keyframe i shares with keyframe i-1,
``T`` the number of map points matched in keyframe i-1.

Eq. 3 looks at the sparse map only. A keyframe it rejects is still taken when the Gaussian map leaves too much of
it unexplained (``Selection.UNCOVERED``, decided by the mapping stage): moving back from a scene, a camera keeps
tracking the same points (``M`` stays near ``T``) while new surfaces enter the image at its borders.
"""

from __future__ import annotations

import enum

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

    @property
    def selected(self) -> bool:
        return self in (Selection.FIRST, Selection.SELECTED, Selection.NO_SPARSE_MAP, Selection.BRIDGE_OFF, Selection.UNCOVERED)


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
