"""Settings of the Fusion Bridge (paper Sec. 3.3)."""

from __future__ import annotations

import dataclasses

from tambridge.settings import FRACTION, NON_NEGATIVE, POSITIVE, UNIT, at_least, setting


@dataclasses.dataclass
class BridgeConfig:
    """Fusion Bridge (paper Sec. 3.3, appendix): view selection and joint pose refinement.

    ``enabled: false`` is the paper's ablation: frontend poses go straight to the mapper and every keyframe is a
    mapping view.
    """

    enabled: bool = setting(True, "select mapping views by eq. 3 and refine their poses against the Gaussian map")
    alpha: float = setting(0.75, "eq. 3: a keyframe sharing this share or more of the previous one's matched points "
                                 "adds nothing new", FRACTION)
    beta: int = setting(20, "eq. 3: a keyframe must share at least this many map points with the previous one",
                        NON_NEGATIVE)
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
    min_gated_fraction: float = setting(0.05, "below this share of gated pixels (and with no matched points) the "
                                              "frontend pose is kept", UNIT)
