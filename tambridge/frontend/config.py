"""Which frontend tracks, and the settings of each."""

from __future__ import annotations

import dataclasses

from tambridge.frontend.open3d.config import Open3dFrontendConfig
from tambridge.frontend.orb.config import OrbFrontendConfig
from tambridge.frontend.smoothing import SmoothingConfig
from tambridge.settings import Choice, section, setting


class FrontendKind(Choice):
    """The tracking frontends."""

    orb = "orb"
    open3d = "open3d"
    open3d_f2f = "open3d_f2f"


@dataclasses.dataclass
class FrontendConfig:
    """Tracking frontend: ``orb`` (default), ``open3d`` (keyframes + pose graph) or ``open3d_f2f`` (frame to frame).

    ``orb`` holds the ORB frontend's settings and ``open3d`` those of both Open3D frontends (frame to frame uses
    its odometry depths only), so every one is reachable from YAML and ``--set frontend.orb.n_features=2000``.
    """

    kind: FrontendKind = setting(FrontendKind.orb, "tracking frontend: orb (ORB-SLAM2 style), open3d (keyframes + pose "
                                                   "graph) or open3d_f2f (frame-to-frame odometry)")
    # Same results either way; it pays only where a core is free for the two workers (they share the GIL).
    prefetch: bool = setting(True, "read the next frames and extract their ORB features in two worker threads while "
                                   "frame i is tracked")
    orb: OrbFrontendConfig = section(OrbFrontendConfig, "settings of the ORB frontend")
    open3d: Open3dFrontendConfig = section(Open3dFrontendConfig, "settings of both Open3D frontends")
    smoothing: SmoothingConfig = section(SmoothingConfig, "the final trajectory smoothed under a motion model, "
                                                          "keyframes kept")
