"""Settings of the Fusion Bridge (paper Sec. 3.3)."""

from __future__ import annotations

import dataclasses

from tambridge.settings import FRACTION, NON_NEGATIVE, POSITIVE, UNIT, at_least, setting


@dataclasses.dataclass
class BridgeConfig:
    """Fusion Bridge (paper Sec. 3.3, appendix): view selection (eq. 3, and the sharpest frame near each keyframe)
    and joint pose refinement.

    ``enabled: false`` is the paper's ablation: frontend poses go straight to the mapper and every keyframe is a
    mapping view.
    """

    enabled: bool = setting(True, "select mapping views by eq. 3 and sharpness (and refine their poses against the "
                                  "Gaussian map with refine_poses)")
    alpha: float = setting(0.75, "eq. 3: a keyframe sharing this share or more of the previous one's matched points "
                                 "adds nothing new", FRACTION)
    beta: int = setting(20, "eq. 3: a keyframe must share at least this many map points with the previous one",
                        NON_NEGATIVE)
    refine_poses: bool = setting(False, "refine each view's pose against the Gaussian map (eqs. 1, 4, 5); off: the "
                                        "views keep their tracked poses (docs/fusion_bridge.md has the measurements)")
    gamma: float = setting(0.99, "eq. 5: pixels take part in the refinement where the rendered silhouette exceeds this",
                           FRACTION)
    w_reprojection: float = setting(1.5, "w1: weight of the keypoint reprojection loss (per pixel)", NON_NEGATIVE)
    w_colour: float = setting(0.5, "w2: weight of the colour L1 loss", NON_NEGATIVE)
    w_depth: float = setting(1.0, "w3: weight of the depth L1 loss (per metre)", NON_NEGATIVE)
    iterations: int = setting(10, "loss evaluations of the L-BFGS pose refinement (a render and its backward pass each)",
                              at_least(1))
    lever_m: float = setting(2.5, "the twist's rotation is scaled so a unit step turns points this far away as far as a "
                                  "unit translation (m)", POSITIVE)
    depth_outlier_factor: float = setting(10.0, "depth gate: a pixel whose depth residual exceeds this many median "
                                                "residuals is an outlier", POSITIVE)
    sharpest_window: int = setting(6, "a selected keyframe is mapped through the sharpest tracked frame among it and "
                                      "this many frames before it that passes eq. 3 (0: the keyframe itself)",
                                   NON_NEGATIVE)
    sharper_by: float = setting(1.5, "a frame of the window replaces the keyframe only when this many times as sharp",
                                at_least(1.0))
    blur_reject_ratio: float = setting(0.35, "a view whose sharpness is below this share of the median over the recent "
                                             "tracked frames is not mapped (0: never skipped)", UNIT)
    sharpness_median_frames: int = setting(60, "tracked frames the recent median sharpness is taken over", at_least(1))
    reprojection_floor_px: float = setting(0.5, "the refinement is skipped where the keyframe's matched points reproject "
                                                "within this mean error at the frontend pose (mapping-resolution px; "
                                                "0: never skipped)", NON_NEGATIVE)
    sharpness_weighted_colour: bool = setting(False, "scale the colour term by the view's sharpness over the recent "
                                                    "median (at most 1): a blurred view pulls its pose less by colour")
    blur_exposure_s: float | None = setting(None, "exposure time of the colour frames (s) for blur-aware mapping: the "
                                                  "mapper renders each view as the mean over the camera's tracked motion "
                                                  "during it (null: the camera file's exposure_s, which tambridge synth "
                                                  "writes, else 0; 0: off)", NON_NEGATIVE)
    blur_step_px: float = setting(1.0, "a blurred view's sub-poses lie at most this far apart in image motion at the "
                                       "rendering resolution (px; motion under it: one sharp render)", POSITIVE)
    blur_max_subposes: int = setting(9, "renders per blurred view at most (odd counts keep the view's own pose among "
                                        "them)", at_least(1))
    blur_steps_factor: int = setting(4, "a view rendered over its exposure (more than one sub-pose) gets this many times "
                                        "the mapping and final Adam steps: a blurred frame says less about the sharp "
                                        "map per step (1: as many as a sharp view)", at_least(1))
    min_gated_fraction: float = setting(0.05, "below this share of gated pixels (and with no matched points) the "
                                              "frontend pose is kept", UNIT)
