"""Run configuration: dataclasses whose defaults are the paper's values; YAML presets and ``--set`` only override.

A config is resolved once (defaults <- preset YAML <- ``key.sub=value`` overrides) and written next to the
results as ``config.yaml``, so every run can be repeated from its output folder.
"""

from __future__ import annotations

import dataclasses
import typing
from pathlib import Path

import yaml

from tambridge.errors import TambridgeError
from tambridge.frontend.types import Open3dFrontendConfig, OrbFrontendConfig


class ConfigError(TambridgeError):
    """A preset or override names an unknown key or gives a value of the wrong type."""


@dataclasses.dataclass
class InputConfig:
    """Which frames of the sequence are read."""

    stride: int = 1
    max_frames: int | None = None
    camera_file: str | None = None


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


@dataclasses.dataclass
class MapperConfig:
    """Online 3DGS mapper (paper Sec. 3.4, appendix).

    Each new mapping view gets ``iterations`` Adam steps, alternating the new view with earlier views of the
    window (the ``window_size - 1`` earlier views that overlap it most); after the frontend finishes, every
    mapping view gets ``final_iterations_per_view`` more at the final poses. Mapping runs on frames resized by
    ``resolution_scale``. Learning rates are 4-10x SplaTAM's: with a few dozen steps per view rather than SplaTAM's
    hundreds they reach a sharper map (measured on the synthetic loop at ground-truth poses: +2 dB PSNR).
    """

    enabled: bool = True
    zeta: float = 0.3
    tau: float = 0.005
    w_depth: float = 0.5
    w_colour: float = 1.0
    iterations: int = 30
    # 160x120 for a 640x480 camera. Measured on 7-Scenes (100 frames, ground-truth poses, bridge on): 0.5 with
    # 60 steps gave +0.1 dB novel-view PSNR over 0.25 with 30 steps, at 4.5x the mapping time.
    resolution_scale: float = 0.25
    window_size: int = 5
    final_iterations_per_view: int = 2
    lr_means_m: float = 5e-4
    lr_rgb: float = 1e-2
    lr_log_radii: float = 1e-2
    lr_opacity_logits: float = 1e-1
    initial_opacity: float = 0.5
    # Per-view affine colour (gain and bias per channel, Adam at lr_exposure) between the map and each view, so
    # that auto exposure along a real sequence does not recolour the map (see gaussians.mapper.ViewExposure).
    exposure_compensation: bool = True
    lr_exposure: float = 1e-2
    # Densify where the border mask is below this (the paper's gamma) or the map lies this many median depth
    # residuals behind the observed depth.
    densify_silhouette: float = 0.99
    densify_depth_factor: float = 50.0
    # Coverage (as SplaTAM and MonoGS add views): every coverage_check_every-th tracked frame after the latest
    # keyframe is rendered at the mapping resolution; where the map leaves coverage_unexplained more of its valid
    # depth pixels unexplained (the densification mask above) than of the view the frame is anchored to, the
    # frontend is asked to make the next frame a keyframe, and a keyframe that eq. 3 rejects is mapped all the same
    # when it is that uncovered. The ORB keyframe rule follows tracked points, not the image area: backing away
    # from the scene it kept tracking the same points and left frames 30-51 of the synthetic loop without a view
    # (novel views there 20-22 dB). Measured on benchmarks/reconstruct.py's synthetic loop (default preset):
    # off 27.87 dB / 0.919 novel views, 11 views; 0.12 every 2 frames 30.36 dB / 0.936, 17 views. Counting from
    # the anchor view's share rather than from 0 leaves real data alone where the map never explains some depth:
    # on 7-Scenes that share is 4-13 % and frames rose at most 8.5 % above it (first 60 frames), while an absolute
    # 15 % asked for 3 keyframes in frames 0-33, which moved the ORB keyframes and their loops (700 frames: ATE
    # 3.09 -> 3.88 cm).
    # 0: off.
    coverage_unexplained: float = 0.12
    coverage_check_every: int = 2
    # Oversized Gaussians (2D radius in the mapped view, pixels of the mapping resolution) are pruned.
    prune_radius_px: float = 20.0
    backend: str = "auto"
    # numba threads of the CPU rasteriser while mapping and evaluating (0: all cores). Mapping runs inline with
    # tracking, so without them one of two cores idles: on the idle 2-core machine (7-Scenes, 150 frames, default
    # preset, two runs each) 2 threads gave 3.66/3.93 frames/s end to end against 3.00/2.94 with 1 (mapping 24 s
    # against 32 s), the same renders. With other processes on the cores 1 is faster (OpenMP threads spin-wait).
    kernel_threads: int = 2


@dataclasses.dataclass
class MeshConfig:
    """TSDF fusion of the final poses into ``mesh.ply``.

    ``source``: ``tsdf`` fuses the sensor depth, ``gaussians`` the depth rendered from the Gaussian map (falls
    back to the sensor depth when no map was built). Every ``frame_stride``-th frame is fused, which keeps the
    cost at a fraction of the run (consecutive frames add little). Voxels seen in fewer than ``min_views`` fused
    views are left out of the mesh (2 or more drops single-view noise but leaves holes where views are sparse).
    """

    enabled: bool = True
    voxel_size_m: float = 0.02
    truncation_m: float = 0.08
    max_depth_m: float = 4.0
    source: str = "tsdf"
    frame_stride: int = 5
    min_views: int = 1


@dataclasses.dataclass
class EvaluationConfig:
    """Which frames are rendered for PSNR/SSIM/LPIPS (every n-th frame as novel views)."""

    novel_view_every: int = 5


@dataclasses.dataclass
class CheckpointConfig:
    """Checkpoints for ``reconstruct --resume``: every ``every_keyframes`` keyframes (0: never) the frontend and
    mapping state are written atomically to ``<output>/checkpoint/``; a finished run removes them."""

    every_keyframes: int = 0


@dataclasses.dataclass
class Config:
    """The whole run configuration."""

    input: InputConfig = dataclasses.field(default_factory=InputConfig)
    frontend: FrontendConfig = dataclasses.field(default_factory=FrontendConfig)
    bridge: BridgeConfig = dataclasses.field(default_factory=BridgeConfig)
    mapper: MapperConfig = dataclasses.field(default_factory=MapperConfig)
    mesh: MeshConfig = dataclasses.field(default_factory=MeshConfig)
    evaluation: EvaluationConfig = dataclasses.field(default_factory=EvaluationConfig)
    seed: int = 0
    checkpoint: CheckpointConfig = dataclasses.field(default_factory=CheckpointConfig)
    # Torch device of the Gaussian map, the bridge and the rendering evaluation: cpu (ships), cuda (gsplat) or
    # auto (cuda when a GPU and gsplat are there); resolved by tambridge.device.resolve_device.
    device: str = "cpu"


def to_dict(config: Config) -> dict:
    return dataclasses.asdict(config)


def dotted_items(values: dict, prefix: str = "") -> dict[str, typing.Any]:
    """Every leaf of a nested dict under its dotted key (``mapper.iterations``), in insertion order."""
    leaves = {}
    for key, value in values.items():
        if isinstance(value, dict):
            leaves.update(dotted_items(value, f"{prefix}{key}."))
        else:
            leaves[f"{prefix}{key}"] = value
    return leaves


def to_yaml(config: Config) -> str:
    return yaml.safe_dump(to_dict(config), sort_keys=False)


def _coerce(value, annotation, key: str):
    """Check/convert a YAML value to a field's annotated type (int, float, bool, str, optional of those)."""
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        options = [a for a in typing.get_args(annotation) if a is not type(None)]
        if value is None or (isinstance(value, str) and value.lower() in ("null", "none")):
            return None
        return _coerce(value, options[0], key)
    if annotation is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false", "on", "off", "yes", "no", "1", "0"):
            return value.lower() in ("true", "on", "yes", "1")
        raise ConfigError(f"{key}: expected true/false, got {value!r}")
    try:
        if annotation is int:
            if isinstance(value, float) and not value.is_integer():
                raise ValueError
            return int(value)
        if annotation is float:
            return float(value)
        if annotation is str:
            return str(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{key}: expected {annotation.__name__}, got {value!r}") from None
    raise ConfigError(f"{key}: unsupported field type {annotation}")


def _apply(target, values: dict, prefix: str) -> None:
    hints = typing.get_type_hints(type(target))
    for key, value in values.items():
        name = f"{prefix}{key}"
        if key not in hints:
            known = ", ".join(hints)
            raise ConfigError(f"unknown config key {name!r}; known keys here: {known}")
        current = getattr(target, key)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, dict):
                raise ConfigError(f"{name}: expected a mapping of {', '.join(typing.get_type_hints(type(current)))}")
            _apply(current, value, f"{name}.")
        else:
            setattr(target, key, _coerce(value, hints[key], name))


def load_config(preset: Path | None = None, overrides: typing.Sequence[str] = ()) -> Config:
    """Defaults, then a YAML preset, then ``section.key=value`` overrides (values parsed as YAML scalars)."""
    config = Config()
    if preset is not None:
        preset = Path(preset)
        if not preset.is_file():
            raise ConfigError(f"{preset}: config file not found; presets live in configs/ (default, fast, quality, open3d)")
        try:
            values = yaml.safe_load(preset.read_text()) or {}
        except yaml.YAMLError as error:
            raise ConfigError(f"{preset}: not valid YAML ({error})") from error
        if not isinstance(values, dict):
            raise ConfigError(f"{preset}: expected a mapping at the top level")
        _apply(config, values, "")
    for override in overrides:
        if "=" not in override:
            raise ConfigError(f"--set {override!r}: expected key=value, e.g. --set mapper.iterations=50")
        key, raw = override.split("=", 1)
        nested: dict = {}
        cursor = nested
        parts = key.strip().split(".")
        for part in parts[:-1]:
            cursor = cursor.setdefault(part, {})
        cursor[parts[-1]] = yaml.safe_load(raw) if raw.strip() else None
        _apply(config, nested, "")
    return config
