"""Settings of the ORB RGB-D frontend, and their adaptation to the image size."""

from __future__ import annotations

import dataclasses
import typing

import numpy as np

from tambridge.settings import FRACTION, NON_NEGATIVE, POSITIVE, UNIT, Choice, Range, at_least, setting

if typing.TYPE_CHECKING:
    from tambridge.camera import Camera


class DenseDepthUse(Choice):
    """When motion-only refinement adds the point-to-plane depth term (tambridge/frontend/orb/dense_depth.py)."""

    never = "never"
    auto = "auto"  # where matches are few or the predicted motion turns fast
    always = "always"


@dataclasses.dataclass
class OrbFrontendConfig:
    """ORB RGB-D frontend settings; defaults are ORB-SLAM2's RGB-D values for a 640x480 Kinect.

    Pixel radii are at pyramid level 0 and grow by ``scale_factor ** level`` for coarser keypoints. With
    ``scale_with_image`` the feature budget, pyramid, border and grid cell are those of a 640x480 image and
    :func:`scaled_for_image` adapts them to the camera's size.
    """

    # A run records the adapted values with this off (tambridge.config.config_for_camera), so config.yaml repeats the run.
    scale_with_image: bool = setting(True, "adapt n_features, n_levels, edge_threshold_px and grid_cell_px from 640x480 "
                                           "to the camera's size (false: use them as given)")

    # Features: cv2 ORB over a scale pyramid, bucketed on a grid per level so they cover the image.
    n_features: int = setting(1500, "ORB features extracted per frame", at_least(1))
    scale_factor: float = setting(1.2, "scale between pyramid levels", Range(1, low_open=True))
    n_levels: int = setting(8, "pyramid levels", at_least(1))
    fast_threshold: int = setting(7, "FAST corner threshold (intensity difference, 0-255)", Range(1, 255))
    grid_cell_px: int = setting(32, "side of the grid cells that features are bucketed in (px)", at_least(1))
    # ORB-SLAM uses 19; tiny images need less.
    edge_threshold_px: int = setting(19, "keypoints nearer the image border than this are not detected (px)",
                                     NON_NEGATIVE)
    min_depth_m: float = setting(0.1, "keypoint depth below this is dropped (m)", NON_NEGATIVE)
    # Colour-depth misregistration makes depth unreliable at depth edges.
    depth_edge_window_px: int = setting(1, "radius of the window a keypoint's depth edge is looked for in (px; 0: keep "
                                           "all depths)", NON_NEGATIVE)
    depth_edge_ratio: float = setting(0.05, "a keypoint's depth is dropped where the depth in its window jumps by more "
                                            "than this fraction", POSITIVE)
    max_depth_m: float = setting(8.0, "keypoint depth beyond this is dropped (m)", POSITIVE)
    # ORB-SLAM's ThDepth of 40 baselines.
    close_depth_m: float = setting(3.2, "points nearer than this are close: their depth is trusted (m)", POSITIVE)
    depth_noise_per_m: float = setting(0.02, "k of the inverse-depth residual's sigma_z = k z^2 in RGB-D bundle "
                                             "adjustment (1/m)", POSITIVE)
    # On: more accurate where colour is registered to depth; unregistered, a corner's depth belongs to another
    # surface and it costs accuracy (depth seeds new points either way).
    depth_residuals: bool = setting(True, "each observation with depth adds an inverse-depth residual to bundle "
                                          "adjustment")
    # TUM's depth images are taken up to 20 ms from their colour images (tambridge/frontend/orb/depth_time.py). On
    # by default since the dense depth term is always on: without it the term cost accuracy on fr1/xyz's first 37
    # frames (docs/benchmarks.md).
    depth_time_compensation: bool = setting(True, "move each frame's depth to its colour image's time with the motion "
                                                   "prior, where the frame's depth has its own timestamp")
    rolling_shutter_s: float | None = setting(None, "the colour camera's rolling-shutter readout, first row to last "
                                                    "(s): each frame's keypoints are moved to its middle row's time "
                                                    "by the camera's motion (null: the camera file's "
                                                    "rolling_shutter_s or the TUM preset's, else 0; 0: global shutter)",
                                              NON_NEGATIVE)
    # Matching by projecting local-map points with the motion prior.
    search_radius_px: float = setting(15.0, "radius searched around a projected local-map point (px)", POSITIVE)
    refine_radius_px: float = setting(4.0, "search radius after the pose refinement (px)", POSITIVE)
    max_hamming: int = setting(100, "largest descriptor distance of a match (bits of 256)", Range(0, 256))
    ratio: float = setting(0.8, "a match's best distance must be below this times the second best", FRACTION)
    local_map_keyframes: int = setting(12, "keyframes whose points make the local map", at_least(1))
    # PnP-RANSAC and motion-only refinement.
    pnp_reprojection_px: float = setting(4.0, "PnP-RANSAC inlier reprojection error (px)", POSITIVE)
    pnp_iterations: int = setting(60, "PnP-RANSAC iterations", at_least(1))
    min_inliers: int = setting(30, "least PnP inliers of a tracked frame", at_least(4))
    relocalisation_min_inliers: int = setting(50, "least PnP inliers of a relocalised frame", at_least(4))
    relocalisation_ransac_min_inliers: int = setting(
        15, "least PnP-RANSAC inliers of a relocalisation's brute-force matches, before the projection search that "
        "must reach relocalisation_min_inliers (a blurred frame matches few points by descriptor alone); also the "
        "end-of-run join of unjoined map segments", at_least(4))
    # Dense point-to-plane depth term against the last keyframe's depth (tambridge/frontend/orb/dense_depth.py); after
    # a relocalisation, until the next keyframe, against the relocalising keyframe's bundle-adjustment maps.
    # always: with the depth moved to the colour time it lowers RPE on fr1/xyz and 7-Scenes and the error in
    # 7-Scenes' fast turns, and no longer costs fr1/xyz's first 37 frames (docs/benchmarks.md).
    dense_depth: DenseDepthUse = setting(DenseDepthUse.always, "add the point-to-plane depth term to motion-only "
                                         "refinement: never, auto (few matches or fast turns) or always")
    dense_depth_weight: float = setting(300.0, "total weight of the depth term, in whitened residuals (its samples "
                                               "share it, so ORB's matches lead where they are many)", POSITIVE)
    dense_depth_noise_per_m: float = setting(0.0025, "k of the depth term's sigma_z = k z^2 at each end (1/m)", POSITIVE)
    dense_depth_huber_sigmas: float = setting(2.0, "Huber threshold of the depth term (sigmas)", POSITIVE)
    dense_depth_max_distance_m: float = setting(0.05, "depth samples farther than this from the keyframe's surface "
                                                      "have no residual (m)", POSITIVE)
    dense_reference_stride_px: int = setting(4, "the keyframe's vertex and normal maps take every n-th pixel",
                                             at_least(1))
    dense_sample_stride_px: int = setting(16, "the frame's depth samples take every n-th pixel", at_least(1))
    dense_auto_max_matches: int = setting(150, "auto: the term is added when fewer map points than this are "
                                               "matched ...", NON_NEGATIVE)
    dense_auto_min_rotation_deg: float = setting(2.0, "... or the motion prior turns by more than this per frame "
                                                      "(degrees; 2 = 60 deg/s at 30 frames/s)", NON_NEGATIVE)
    # A frame ORB cannot place (blur, texture gone, a covered lens) often still has its depth; projective ICP from
    # the motion prior recovers 1-5 cm of motion to about a centimetre on fr1/xyz (docs/benchmarks.md).
    depth_only_tracking: bool = setting(True, "a frame that neither ORB tracking nor relocalisation can place is "
                                              "tracked by the depth term alone against the last keyframe, where the "
                                              "two bounds below hold (needs dense_depth other than never)")
    depth_only_min_share: float = setting(0.6, "... the share of the frame's depth samples on the keyframe's surface "
                                               "at the pose found, at least", UNIT)
    depth_only_min_conditioning: float = setting(1e-3, "... and the smallest over the largest eigenvalue of the depth "
                                                       "term's Gauss-Newton matrix there (a single plane leaves motions "
                                                       "free: near 0)", NON_NEGATIVE)
    # Depth edges between consecutive keyframes in bundle adjustment lower ATE on fr1/xyz and 7-Scenes; heavier
    # than 1000 they cost 7-Scenes' fast turns and, past 3000, fr1/xyz (docs/benchmarks.md).
    ba_dense_depth: bool = setting(True, "bundle adjustment ties each keyframe to the previous one by the "
                                         "point-to-plane depth term")
    ba_dense_depth_weight: float = setting(1000.0, "total weight of a depth edge in bundle adjustment, in whitened "
                                                  "residuals", POSITIVE)
    ba_dense_neighbours: int = setting(1, "bundle adjustment ties each keyframe to this many previous ones of its "
                                          "segment", at_least(1))
    ba_dense_reference_stride_px: int = setting(8, "a keyframe's vertex and normal maps for bundle adjustment take "
                                                   "every n-th pixel", at_least(1))
    # Keyframe insertion as ORB-SLAM2's.
    keyframe_tracked_ratio: float = setting(0.75, "a frame tracking fewer than this share of its reference keyframe's "
                                                  "points may become a keyframe", UNIT)
    keyframe_min_frames: int = setting(8, "frames after the last keyframe before one is inserted", NON_NEGATIVE)
    # The rule above makes a keyframe about every keyframe_min_frames frames wherever the camera is (a frame rarely
    # tracks keyframe_tracked_ratio of a keyframe's points), so a camera back where it has been adds keyframes that
    # repeat old ones, and a long session's keyframes, map and cost grow with its frames (docs/benchmarks.md).
    keyframe_revisit_distance_m: float = setting(0.0, "a keyframe due for coverage alone (not for weak tracking or "
                                                      "the mapper) is not made where a live keyframe of the frame's "
                                                      "map segment lies within this distance (m; 0: off) ...",
                                                 NON_NEGATIVE)
    keyframe_revisit_angle_deg: float = setting(4.0, "... and this rotation (degrees) of the frame", POSITIVE)
    min_new_points: int = setting(100, "a new keyframe makes at least this many map points (the closest)", NON_NEGATIVE)
    # ORB-SLAM2's "close points" trigger.
    keyframe_close_tracked: int = setting(100, "close-points keyframe trigger: fewer than this close points tracked ...",
                                          NON_NEGATIVE)
    keyframe_close_untracked: int = setting(70, "... and more than this close points not tracked", NON_NEGATIVE)
    covisibility_min_shared: int = setting(15, "keyframes sharing at least this many points are covisible", at_least(1))
    distinctive_descriptors: bool = setting(True, "a map point's descriptor is the most typical of its observations "
                                                  "(false: the first)")
    # Off by default: it can change which loops verify and so cost accuracy; it pays where the camera lingers
    # (fewer keyframes for local BA, the pose graph and the keyframe database).
    keyframe_culling: bool = setting(False, "after local BA, drop keyframes whose close points are over 90 % seen by 3 "
                                            "other keyframes (ORB-SLAM's culling)")
    # Local BA over the new keyframe and its best covisible keyframes.
    local_ba_keyframes: int = setting(10, "keyframes optimised by local BA (the new one and its best covisible)",
                                      at_least(1))
    local_ba_iterations: int = setting(6, "LM steps of local BA, rejected ones included (0: none)", NON_NEGATIVE)
    # Loop closure and global BA.
    loop_closure: bool = setting(True, "detect and close loops with the keyframe database")
    vocabulary_path: str | None = setting(None, "ORB vocabulary .npz (null: the one shipped in tambridge/frontend/orb/data)")
    loop_min_inliers: int = setting(40, "least PnP inliers verifying a loop", at_least(4))
    loop_candidates: int = setting(3, "loop candidates verified per keyframe", at_least(1))
    loop_min_score_ratio: float = setting(0.75, "loop candidates score at least this times the lowest score of the "
                                                "covisible keyframes", NON_NEGATIVE)
    loop_cooldown_keyframes: int = setting(10, "keyframes after a loop before the next is looked for", NON_NEGATIVE)
    loop_consistency: int = setting(3, "a loop candidate must have been one for this many keyframes before (0: any)",
                                    NON_NEGATIVE)
    global_ba: bool = setting(True, "global bundle adjustment once the last frame is tracked")
    global_ba_iterations: int = setting(5, "LM steps of global BA, rejected ones included", NON_NEGATIVE)
    # Inline keyframe work is deterministic; the thread overlaps it with tracking.
    mapping_thread: bool = setting(True, "keyframe work (fusion, local BA, loop closing) in a background thread "
                                         "(false: inline)")

    def conflict(self) -> str | None:
        if self.min_depth_m >= self.max_depth_m:
            return f"min_depth_m={self.min_depth_m:g} must be below max_depth_m={self.max_depth_m:g}"
        return None

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
    values tuned by hand for the synthetic tests); the depth term's pixel strides scale by ``s``. The pyramid keeps levels while the short side stays at or above
    MIN_PYRAMID_SIDE_PX (4 levels at 160x120). Error thresholds in pixels stay as they are (keypoint noise is
    about a pixel at any size), and so do the keyframe point counts: scaled down, they gave fewer keyframes and a
    worse trajectory on the 160x120 synthetic loop (docs/benchmarks.md).
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
        # The depth term's grids keep their share of the image.
        dense_reference_stride_px=max(1, int(round(config.dense_reference_stride_px * factor * factor))),
        dense_sample_stride_px=max(1, int(round(config.dense_sample_stride_px * factor * factor))),
    )


def for_camera(config: OrbFrontendConfig, camera: "Camera") -> OrbFrontendConfig:
    """``config`` as the frontend runs it on ``camera``: :func:`scaled_for_image` to its size, and its
    rolling-shutter readout where ``rolling_shutter_s`` is null."""
    config = scaled_for_image(config, camera.width, camera.height)
    if config.rolling_shutter_s is None:
        config = dataclasses.replace(config, rolling_shutter_s=camera.rolling_shutter_s)
    return config
