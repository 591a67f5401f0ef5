"""Which frontend tracks, and the settings of each."""

from __future__ import annotations

import dataclasses

from tambridge.frontend.open3d.config import Open3dFrontendConfig
from tambridge.frontend.orb.config import OrbFrontendConfig


@dataclasses.dataclass
class FrontendConfig:
    """Tracking frontend: ``orb`` (default), ``open3d`` (keyframes + pose graph) or ``open3d_f2f`` (frame to frame).

    ``orb`` holds the ORB frontend's settings and ``open3d`` those of both Open3D frontends (frame to frame uses
    its odometry depths only), so every one is reachable from YAML and ``--set frontend.orb.n_features=2000``.
    """

    kind: str = "orb"
    # Read frame i+2 and extract frame i+1's ORB features in two worker threads while frame i is tracked; same
    # results. It needs a free core: on 7-Scenes (700 frames, 2 cores) with the machine otherwise nearly idle (load
    # 1-1.5) end to end 23.9 -> 31.5 frames/s with the mapping thread, 20.0 -> 21.7 inline (one worker, colour as
    # recorded); with the cores busy with other work (load 3-5) -9 to +7 % with the mapping thread, -4 to 0 % inline
    # (the threads also share the GIL). Reading registered 7-Scenes (colour resampled, ~10 ms more per frame), the
    # second worker took idle runs from 22.0-24.1 to 25.6-26.6 frames/s.
    prefetch: bool = True
    orb: OrbFrontendConfig = dataclasses.field(default_factory=OrbFrontendConfig)
    open3d: Open3dFrontendConfig = dataclasses.field(default_factory=Open3dFrontendConfig)
