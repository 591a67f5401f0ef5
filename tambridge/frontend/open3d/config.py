"""Settings of the Open3D frontends (keyframe pose graph and frame to frame)."""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass
class Open3dFrontendConfig:
    """Open3D frontend: hybrid RGB-D odometry to the last keyframe, a keyframe pose graph with verified loop edges."""

    max_depth_m: float = 4.0
    depth_diff_max_m: float = 0.07
    keyframe_translation_m: float = 0.10
    keyframe_rotation_deg: float = 10.0
    keyframe_max_frames: int = 30
    # Loop candidates: keyframes whose camera centres and viewing directions are close.
    loop_radius_m: float = 0.5
    loop_max_angle_deg: float = 30.0
    loop_min_keyframe_gap: int = 5
    loop_max_candidates: int = 2
    # Verification by Open3D registration (point-to-plane ICP on voxel-downsampled clouds).
    loop_voxel_m: float = 0.02
    loop_icp_distance_m: float = 0.05
    loop_min_fitness: float = 0.3
    loop_max_rmse_m: float = 0.03
    # Open3D global_optimization options (as in Open3D's reconstruction system).
    edge_prune_threshold: float = 0.25
    preference_loop_closure: float = 0.1
