"""Tracking-centred frontends: ORB RGB-D SLAM (default) and Open3D RGB-D odometry with a keyframe pose graph.

Both follow :class:`~tambridge.frontend.types.Frontend`: ``track(frame) -> TrackResult`` per frame,
``keyframe_poses()`` at any time, ``finish() -> FrontendResult`` at the end. The frontends themselves live in
:mod:`~tambridge.frontend.orb_frontend` and :mod:`~tambridge.frontend.open3d_frontend`; they are not imported
here, so that importing the light types (as :mod:`tambridge.config` does) does not load Open3D and numba.
"""

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
    "STAGES", "Frontend", "FrontendResult", "KeyframeEvent", "Open3dFrontendConfig", "OrbFrontendConfig", "TrackResult",
]
