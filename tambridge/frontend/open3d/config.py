"""Settings of the Open3D frontends (keyframe pose graph and frame to frame)."""

from __future__ import annotations

import dataclasses

from tambridge.settings import NON_NEGATIVE, POSITIVE, UNIT, Range, at_least, setting


@dataclasses.dataclass
class Open3dFrontendConfig:
    """Open3D frontend: hybrid RGB-D odometry to the last keyframe, a keyframe pose graph with verified loop edges."""

    max_depth_m: float = setting(4.0, "odometry ignores depth beyond this (m; above its fixed 0.1 m minimum)",
                                 Range(0.1, low_open=True))
    depth_diff_max_m: float = setting(0.07, "odometry correspondences whose depths differ more than this are dropped (m)",
                                      POSITIVE)
    keyframe_translation_m: float = setting(0.10, "a frame moved more than this from the last keyframe becomes one (m)", POSITIVE)
    keyframe_rotation_deg: float = setting(10.0, "a frame turned more than this from the last keyframe becomes one (degrees)",
                                           Range(0, 180, low_open=True))
    keyframe_max_frames: int = setting(30, "a frame this many frames after the last keyframe becomes one", at_least(1))
    # Loop candidates: keyframes whose camera centres and viewing directions are close.
    loop_radius_m: float = setting(0.5, "loop candidates: keyframes whose camera centre is within this (m)", POSITIVE)
    loop_max_angle_deg: float = setting(30.0, "loop candidates: keyframes whose viewing direction is within this (degrees)",
                                        Range(0, 180))
    loop_min_keyframe_gap: int = setting(5, "loop candidates are at least this many keyframes older", at_least(1))
    loop_max_candidates: int = setting(2, "nearest loop candidates verified per keyframe (0: no loop closure)",
                                       NON_NEGATIVE)
    # Verification by Open3D registration (point-to-plane ICP on voxel-downsampled clouds).
    loop_voxel_m: float = setting(0.02, "loop verification: voxel size of the downsampled clouds (m)", POSITIVE)
    loop_icp_distance_m: float = setting(0.05, "loop verification: ICP correspondence distance (m)", POSITIVE)
    loop_min_fitness: float = setting(0.3, "loop verification: least share of points with an ICP correspondence", UNIT)
    loop_max_rmse_m: float = setting(0.03, "loop verification: largest ICP inlier RMSE (m)", POSITIVE)
    # Open3D global_optimization options, as in Open3D's reconstruction system.
    edge_prune_threshold: float = setting(0.25, "pose graph: loop edges whose line-process weight falls below this are "
                                                "pruned", UNIT)
    preference_loop_closure: float = setting(0.1, "pose graph: weight of loop edges against odometry edges", NON_NEGATIVE)
