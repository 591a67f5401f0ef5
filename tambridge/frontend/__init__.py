"""Tracking-centred frontends: ORB RGB-D SLAM (default) and Open3D RGB-D odometry with a keyframe pose graph.

Both follow :class:`~tambridge.frontend.types.Frontend`: ``track(frame) -> TrackResult`` per frame,
``keyframe_poses()`` at any time, ``finish() -> FrontendResult`` at the end.
"""

from tambridge.frontend.open3d_frontend import Open3dFrontend
from tambridge.frontend.orb_frontend import OrbFrontend
from tambridge.frontend.types import (
    STAGES,
    Frontend,
    FrontendResult,
    KeyframeEvent,
    Open3dFrontendConfig,
    OrbFrontendConfig,
    TrackResult,
)

__all__ = [
    "STAGES", "Frontend", "FrontendResult", "KeyframeEvent", "Open3dFrontend", "Open3dFrontendConfig", "OrbFrontend",
    "OrbFrontendConfig", "TrackResult",
]
