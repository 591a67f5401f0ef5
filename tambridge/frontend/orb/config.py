"""Settings of the ORB RGB-D frontend, and their adaptation to the image size."""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass
class OrbFrontendConfig:
    """ORB RGB-D frontend settings; defaults are ORB-SLAM2's RGB-D values for a 640x480 Kinect.

    Pixel radii are at pyramid level 0 and grow by ``scale_factor ** level`` for coarser keypoints. With
    ``scale_with_image`` the feature budget, pyramid, border and grid cell are those of a 640x480 image and
    :func:`scaled_for_image` adapts them to the camera's size.
    """

    # False: the values below are used as given, whatever the image size.
    scale_with_image: bool = True

    # Features: cv2 ORB over a scale pyramid, bucketed on a grid per level so they cover the image.
    n_features: int = 1500
    scale_factor: float = 1.2
    n_levels: int = 8
    fast_threshold: int = 7
    grid_cell_px: int = 32
    # Keypoints nearer the border than this are not detected (ORB-SLAM: 19; smaller for tiny images).
    edge_threshold_px: int = 19
    min_depth_m: float = 0.1
    # A keypoint's depth is dropped where the depth around it (window radius in px) jumps by more than this
    # fraction: depth edges, where colour-depth misregistration makes depth unreliable (0 px: keep all).
    depth_edge_window_px: int = 1
    depth_edge_ratio: float = 0.05
    max_depth_m: float = 8.0
    # Points closer than this (ORB-SLAM's ThDepth = 40 baselines) are "close": their depth is trusted.
    close_depth_m: float = 3.2
    # RGB-D BA: each observation with depth adds an inverse-depth residual with sigma_z = k z^2 (k below).
    # On: with 7-Scenes read registered (configs/cameras/7scenes_kinect.yaml) it brings the 700-frame ATE from
    # 5.36 to 3.91 cm (k = 0.005: 3.69 cm) and the depth misalignment of revisits (benchmarks/revisit_consistency.py)
    # from 15.2 to 13.2 mm (11.25; the ground truth's poses: 11.8); on TUM fr1/xyz 0.61 against 0.59 cm off (k = 0.005: 0.73, fr1's depth has a
    # scale error); on clean synthetic depth 1.0 against 7.9 cm at 160x120 with k = 0.003, the sensor's own noise.
    # With colour not registered to depth it costs accuracy (7-Scenes read as recorded: 4.0 against 3.1 cm), as
    # the depth then belongs to another surface than the corner. Depth always seeds new points.
    depth_noise_per_m: float = 0.02
    depth_residuals: bool = True
    # Matching by projecting local-map points with the motion prior.
    search_radius_px: float = 15.0
    refine_radius_px: float = 4.0
    max_hamming: int = 100
    ratio: float = 0.8
    local_map_keyframes: int = 12
    # PnP-RANSAC and motion-only refinement.
    pnp_reprojection_px: float = 4.0
    pnp_iterations: int = 60
    min_inliers: int = 30
    relocalisation_min_inliers: int = 50
    # Keyframe insertion (ORB-SLAM2): tracked-point ratio to the reference keyframe, frames since the last one.
    keyframe_tracked_ratio: float = 0.75
    keyframe_min_frames: int = 8
    min_new_points: int = 100
    # ORB-SLAM2's "close points" keyframe trigger: fewer than the first tracked and more than the second not.
    keyframe_close_tracked: int = 100
    keyframe_close_untracked: int = 70
    covisibility_min_shared: int = 15
    distinctive_descriptors: bool = True
    # Keyframe culling (ORB-SLAM's KeyFrameCulling, after local BA): a keyframe whose close points are over 90%
    # seen by at least 3 other keyframes at a similar or finer scale leaves the map and follows a parent keyframe.
    # Off by default: on 7-Scenes (700 frames, inline mapping, deterministic) it culled 14 of 85 keyframes and cost
    # ATE, 3.42 vs 3.09 cm, by finding one loop instead of two (the first loop's PnP verification is marginal
    # there: 48 inliers for 40 needed, and a changed map tips it); with the mapping thread one run each gave 3.56
    # vs 3.42 cm (threaded runs vary by about 0.2 cm from run to run). fr1/xyz (37 frames, 4 keyframes) culls none.
    # It pays where the camera lingers: fewer keyframes for local BA, the pose graph and the keyframe database.
    keyframe_culling: bool = False
    # Local BA over the new keyframe and its best covisible keyframes.
    local_ba_keyframes: int = 10
    local_ba_iterations: int = 6
    # Loop closure and global BA.
    loop_closure: bool = True
    vocabulary_path: str | None = None  # None: the vocabulary shipped in tambridge/frontend/orb/data
    loop_min_inliers: int = 40
    loop_candidates: int = 3
    loop_min_score_ratio: float = 0.75
    loop_cooldown_keyframes: int = 10
    # A loop candidate must have been one (or covisible with one) for this many consecutive keyframes before.
    loop_consistency: int = 3
    global_ba: bool = True
    global_ba_iterations: int = 10
    # Keyframe work (fusion, local BA, loop closing) in a background thread; False: inline and deterministic.
    mapping_thread: bool = True

    @property
    def depth_noise(self) -> float:
        """k of the inverse-depth residual, 0 when depth residuals are off."""
        return self.depth_noise_per_m if self.depth_residuals else 0.0


REFERENCE_IMAGE_PX = (640, 480)
"""The image size (width, height) that OrbFrontendConfig's counts and pixel sizes are given for."""
MIN_PYRAMID_SIDE_PX = 64
"""The coarsest pyramid level keeps at least this many pixels on the image's short side."""


def scaled_for_image(config: OrbFrontendConfig, width: int, height: int) -> OrbFrontendConfig:
    """``config`` adapted to a ``width`` x ``height`` image (the same object when nothing changes).

    With the linear size ratio ``s = sqrt(area / 640x480)``, the feature budget, the border and the grid cell
    scale by ``sqrt(s)``: a smaller image holds fewer distinct corners, but ORB's 31 px patch does not shrink with
    it, so they cannot scale with the area (at 160x120: 750 features, a 10 px border, 16 px cells, close to the
    values tuned by hand for the synthetic tests). The pyramid keeps levels while the short side stays at or above
    MIN_PYRAMID_SIDE_PX (4 levels at 160x120). Error thresholds in pixels stay as they are (keypoint noise is
    about a pixel at any size), and so do the keyframe point counts: scaled down, they gave fewer keyframes and a
    worse trajectory on the 30-frame 160x120 synthetic loop (8 keyframes, 2.5 cm ATE, against 18 and 1.1 cm).
    """
    if not config.scale_with_image or (width, height) == REFERENCE_IMAGE_PX:
        return config
    factor = np.sqrt(np.sqrt(width * height / float(np.prod(REFERENCE_IMAGE_PX))))
    levels_that_fit = 1 + int(np.floor(np.log(min(width, height) / MIN_PYRAMID_SIDE_PX) / np.log(config.scale_factor)))
    scale = lambda value, minimum: max(minimum, int(round(value * factor)))  # noqa: E731
    return dataclasses.replace(
        config,
        n_features=scale(config.n_features, 100),
        n_levels=max(1, min(config.n_levels, levels_that_fit)),
        edge_threshold_px=scale(config.edge_threshold_px, 4),
        grid_cell_px=scale(config.grid_cell_px, 8),
    )
