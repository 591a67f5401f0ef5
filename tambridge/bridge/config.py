"""Settings of the Fusion Bridge (paper Sec. 3.3)."""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass
class BridgeConfig:
    """Fusion Bridge (paper Sec. 3.3, appendix): view selection and joint pose refinement.

    ``enabled: false`` is the paper's ablation: frontend poses go straight to the mapper and every keyframe is a
    mapping view.
    """

    enabled: bool = True
    alpha: float = 0.75
    beta: int = 20
    gamma: float = 0.99
    w_reprojection: float = 1.5
    w_colour: float = 0.5
    w_depth: float = 1.0
    # Loss evaluations of the L-BFGS pose refinement (a render and its backward pass each).
    iterations: int = 10
    # The twist's rotation is scaled so that a unit step turns points this far away as far as a unit translation.
    lever_m: float = 2.5
    # Depth gate: a pixel whose depth residual exceeds this many median residuals is an outlier.
    depth_outlier_factor: float = 10.0
    # Below this share of gated pixels (and with no matched points) the frontend pose is kept as it is.
    min_gated_fraction: float = 0.05
