"""Settings of the online 3DGS mapper (paper Sec. 3.4)."""

from __future__ import annotations

import dataclasses

from tambridge.settings import FRACTION, NON_NEGATIVE, POSITIVE, UNIT, Choice, Range, at_least, setting


class ExposureAnchor(Choice):
    """What fixes the map's colour scale, which per-view exposures leave free (see gaussians.mapper.ViewExposure)."""

    median = "median"
    first_view = "first_view"


class RenderBackend(Choice):
    """The rasteriser backends (:mod:`tambridge.gaussians.rasterizer`)."""

    auto = "auto"
    cpu = "cpu"
    reference = "reference"
    gsplat = "gsplat"


@dataclasses.dataclass
class MapperConfig:
    """Online 3DGS mapper (paper Sec. 3.4, appendix).

    Each new mapping view gets ``iterations`` Adam steps, alternating the new view with earlier views of the
    window (the ``window_size - 1`` earlier views that overlap it most); after the frontend finishes, every
    mapping view gets ``final_iterations_per_view`` more at the final poses. Mapping runs on frames resized by
    ``resolution_scale``; a last sharpening pass (``sharp_*``) runs at ``sharp_resolution_scale``, closer to where a
    user views the map (never coarser than the mapping), over the views and ``sharp_frames_between`` tracked frames
    between each view and the next (at ``sharp_between_resolution_scale``; never a frame the evaluation scores).
    Learning rates are 4-10x SplaTAM's: with a few dozen steps per view rather than SplaTAM's hundreds they reach a
    sharper map (docs/benchmarks.md).
    """

    enabled: bool = setting(True, "build the Gaussian map (false: tracking, trajectory and sensor-depth mesh only)")
    zeta: float = setting(0.3, "weight of the SSIM term against the L1 terms in the mapping loss", UNIT)
    tau: float = setting(0.005, "Gaussians less opaque than this are pruned", Range(0, 1, high_open=True))
    w_depth: float = setting(0.5, "weight of the depth L1 loss in mapping (per metre)", NON_NEGATIVE)
    w_colour: float = setting(1.0, "weight of the colour L1 loss in mapping", NON_NEGATIVE)
    iterations: int = setting(30, "Adam steps per new mapping view", NON_NEGATIVE)
    # A quarter of the frame keeps mapping inline with tracking on a CPU; finer scales cost far more time than
    # they add detail.
    resolution_scale: float = setting(0.25, "mapping runs on frames resized by this (0.25: 160x120 for 640x480)",
                                      FRACTION)
    window_size: int = setting(5, "views optimised together: the new one and the earlier ones overlapping it most",
                               at_least(1))
    final_iterations_per_view: int = setting(2, "Adam steps per mapping view at the final poses after tracking",
                                             NON_NEGATIVE)
    # The map is viewed at the camera's resolution, not the mapping one: a last pass at a finer one builds the
    # detail (edges, texture) that the coarse online mapping cannot see. Frames are read again, a window at a time.
    # Half the camera's resolution scores as the full one does (Gaussians sized at the mapping resolution hold no
    # finer detail) at two thirds of the cost, which pays for a second round (docs/benchmarks.md, "Half resolution").
    sharp_resolution_scale: float = setting(0.5, "the sharpening pass after the final one runs on frames resized by "
                                                 "this (1: the camera's resolution; never under resolution_scale)",
                                            Range(0, 2, low_open=True))
    sharp_iterations_per_view: int = setting(2, "Adam steps per mapping view in the sharpening pass (0: off), one "
                                                "round over the views each", NON_NEGATIVE)
    # The views alone are sparse samples of the path: a map fitted to them generalises poorly to the frames between
    # them, which a viewer shows. The evaluation's novel views are never among these frames.
    sharp_frames_between: int = setting(2, "the sharpening pass also fits this many tracked frames between each "
                                           "view and the next, one from each equal share of the frames there (its "
                                           "sharpest with the bridge on, else its middle; never a held-out "
                                           "evaluation frame)", NON_NEGATIVE)
    # Half resolution scores as well as full at less cost (docs/benchmarks.md, "Frames between the views").
    sharp_between_resolution_scale: float = setting(0.5, "... fitted on frames resized by this (1: the camera's "
                                                         "resolution; never under resolution_scale)",
                                                    Range(0, 2, low_open=True))
    # Larger steps first, then annealed: at the online rates throughout, the map ends on whichever frames the pass
    # fitted last (their exposure, their poses' errors); annealing alone leaves it under-fitted (docs/benchmarks.md,
    # "Learning rates in the pass").
    sharp_lr_scale_start: float = setting(2.0, "the sharpening pass's learning rates, as multiples of the online ones "
                                               "(lr_*), fall linearly over the pass from this ...", POSITIVE)
    sharp_lr_scale_end: float = setting(0.1, "... to this (equal: constant)", POSITIVE)
    # PSNR is a squared-error figure: where the frames disagree on a surface's colour (auto exposure, reflections,
    # poses a pixel off) the squared term moves it to their mean, which scores higher than L1's median, for a
    # little SSIM (docs/benchmarks.md, "A squared colour term in the pass").
    sharp_w_colour_squared: float = setting(10.0, "weight of the squared colour error (mean over pixels and "
                                                  "channels) added to the mapping loss in the sharpening pass "
                                                  "(0: the online loss alone)", NON_NEGATIVE)
    # Kept frames spare the later rounds' reads for up to this much more peak memory: worth it for the quality
    # preset's four rounds, too little saved for the default's two (docs/benchmarks.md, "The pass keeps its frames").
    sharp_frames_kept_mb: float = setting(0.0, "frames the sharpening pass reads in its first round are kept for "
                                               "its later rounds (colour as read, uint8) up to this many MB; the "
                                               "rest are read again (0: every round reads every frame)",
                                          NON_NEGATIVE)
    # The views' exposures keep the online map in the median view's colours, which no recorded frame shows; fitted
    # to the frames as recorded, the map's colours become what the frames that see each surface show, which is what
    # a viewer of splats.ply shows: more PSNR as exported at the same cost (docs/benchmarks.md, "Sharp splats").
    sharp_through_exposures: bool = setting(False, "the sharpening pass renders each view through its exposure "
                                                   "(false: fits the frames as recorded, with no exposure)")
    # Off by default: with tracked poses the added Gaussians copy one view's detail where the others disagree, and
    # novel views render worse (docs/benchmarks.md).
    sharp_densify_error: float = setting(0.0, "before the sharpening steps, a Gaussian is added at each pixel whose "
                                              "colour error (mean over channels) exceeds this (0: none)", UNIT)
    sharp_densify_fraction: float = setting(0.02, "... at most at this share of a view's pixels, the worst first",
                                            UNIT)
    # The depth camera measures nothing too close, on dark or shiny surfaces; Gaussians only where it did leave holes
    # that views nearby show black (docs/benchmarks.md, "Holes where the depth camera measured nothing").
    densify_unmeasured: float = setting(0.5, "while mapping, each pixel of a view without measured depth where the "
                                             "map's silhouette is below this gets a Gaussian at the nearest measured "
                                             "depth (0: none)", UNIT)
    rolling_shutter_images: bool = setting(True, "with a rolling-shutter camera (frontend.orb.rolling_shutter_s), "
                                                 "the colour images the map is fitted to are first resampled to a "
                                                 "global shutter at their frame's time by the tracked motion")
    lr_means_m: float = setting(5e-4, "Adam learning rate of the Gaussian centres (m)", POSITIVE)
    lr_rgb: float = setting(1e-2, "Adam learning rate of the colours", POSITIVE)
    lr_log_radii: float = setting(1e-2, "Adam learning rate of the log radii", POSITIVE)
    lr_opacity_logits: float = setting(1e-1, "Adam learning rate of the opacity logits", POSITIVE)
    initial_opacity: float = setting(0.5, "opacity of a new Gaussian", Range(0, 1, low_open=True, high_open=True))
    # Auto exposure along a real sequence would otherwise recolour the map (see gaussians.mapper.ViewExposure).
    exposure_compensation: bool = setting(True, "a per-view affine colour (gain and bias per channel) between the map "
                                                "and each view")
    lr_exposure: float = setting(1e-2, "Adam learning rate of the per-view exposure", POSITIVE)
    exposure_anchor: ExposureAnchor = setting(ExposureAnchor.median, "while mapping, the map's colours are those of: "
                                              "median (the median view's exposure) or first_view (the first view's); "
                                              "a sharpening pass as recorded then fits the frames' own")
    exposure_prior: float = setting(0.0, "weight of the prior pulling each view's exposure to the identity (against "
                                         "the gain-colour ambiguity; 0: none)", NON_NEGATIVE)
    densify_silhouette: float = setting(0.99, "densify where the rendered silhouette is below this (the paper's gamma)",
                                        FRACTION)
    densify_depth_factor: float = setting(50.0, "... or where the map lies this many median depth residuals behind the "
                                                "observed depth", POSITIVE)
    # The ORB keyframe rule follows tracked points, not the image area: backing away from the scene it keeps
    # tracking the same points and leaves new surfaces without a view. Counting from the anchor view's share rather
    # than from 0 leaves real data alone where the map never explains some depth.
    coverage_unexplained: float = setting(0.12, "a tracked frame leaving this share more of its depth unexplained "
                                                "than its anchor view asks for a keyframe (0: off)", UNIT)
    coverage_check_every: int = setting(2, "every n-th tracked frame after the latest keyframe is checked for coverage",
                                        at_least(1))
    prune_radius_px: float = setting(20.0, "Gaussians larger than this in the mapped view are pruned (px of the "
                                           "mapping resolution)", POSITIVE)
    backend: RenderBackend = setting(RenderBackend.auto, "rasteriser: auto (gsplat on CUDA, else cpu), cpu, gsplat or "
                                                         "reference (the slow torch twin)")
    # Mapping runs inline with tracking, so with one thread a core idles; with other processes on the cores one
    # is faster (OpenMP threads spin-wait).
    kernel_threads: int = setting(2, "numba threads of the CPU rasteriser while mapping and evaluating (0: all cores)",
                                  NON_NEGATIVE)
