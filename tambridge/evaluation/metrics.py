"""``metrics.json``, the figures of a finished ``reconstruct`` run, as typed dataclasses: written and read here only.

The file is one JSON object: ``schema_version`` (:data:`SCHEMA_VERSION`) and the fields of :class:`RunMetrics`,
each under its own name, nested dataclasses as nested objects. Two are written into the top level instead (their
fields are top-level keys): :attr:`RunMetrics.map` (absent with the mapper off) and :attr:`RunMetrics.device`.
A field marked :data:`OMITTED_WHEN_NONE` is left out of the file when None; every other None is written as null.
:func:`read_metrics` refuses, with one line naming the file, anything else: so a reader meets a renamed or
missing figure as an error, never as a silent None.
"""

from __future__ import annotations

import dataclasses
import json
import typing
from pathlib import Path

from tambridge.errors import TambridgeError
from tambridge.files import atomic_write_text
from tambridge.settings import Choice

SCHEMA_VERSION = 2
"""Bumped whenever a key of metrics.json is added, renamed or removed, or changes meaning."""

OMITTED_WHEN_NONE = {"omitted_when_none": True}
"""Field metadata: the key is absent from the file when the value is None (rather than null)."""
IN_PARENT = {"in_parent": True}
"""Field metadata: the (dataclass) value's fields are keys of the enclosing object; all absent when it is None."""


@dataclasses.dataclass(kw_only=True)
class TrajectoryMetrics:
    """ATE and RPE against the ground truth, as :meth:`~tambridge.evaluation.trajectory.TrajectoryErrors.summary`
    gives them: metres, degrees; ``scale`` of the alignment (1 for SE(3))."""

    alignment: str
    pose_count: int
    ate_rmse_m: float
    ate_mean_m: float
    ate_median_m: float
    ate_max_m: float
    rpe_trans_rmse_m: float
    rpe_rot_rmse_deg: float
    scale: float


@dataclasses.dataclass(kw_only=True)
class ViewScores:
    """Mean rendering scores over ``frames`` frames (None without frames; ``lpips`` None without its weights), as
    :meth:`~tambridge.evaluation.rendering.RenderingScores.summary` gives them."""

    frames: int
    psnr_db: float | None
    ssim: float | None
    lpips: float | None


class ScoredAgainst(Choice):
    """What renders are scored against: a sequence's sharp ground-truth images (``gt_rgb/``) or its input frames."""

    sharp_ground_truth = "sharp_ground_truth"
    input = "input"


@dataclasses.dataclass(kw_only=True)
class ExportedViewScores:
    """The map as a user gets it: ``splats.ply`` reloaded and rendered with no per-view exposure at the poses of
    ``trajectory.txt``, scored as :class:`ViewScores` are (full resolution, inside the valid region).

    ``ssim_mapping_resolution``: the same renders and frames area-averaged to the mapping resolution (what the
    map resolves; the gap to ``ssim`` is what a viewer at full resolution loses to soft splats).
    ``first_view_colour_ratio``, ``last_view_colour_ratio``: per channel (R, G, B), the mean of the render over
    the mean of the frame, at the first and the last mapping view, over the pixels the map covers (1: true colour;
    None where it covers none).
    """

    frames: int
    psnr_db: float | None
    ssim: float | None
    lpips: float | None
    ssim_mapping_resolution: float | None
    first_view_colour_ratio: list[float] | None
    last_view_colour_ratio: list[float] | None


@dataclasses.dataclass(kw_only=True)
class RenderingMetrics:
    """The map rendered at full resolution, scored against ``scored_against``: at the novel (evaluation) views and
    at the mapping views through each view's exposure (as the run optimised it, or after a sharpening pass against
    the frames as recorded refitted to the final map), and at the novel views as exported (no exposure).
    ``novel_views_sharper_half``: the novel views whose input frames are the sharper half (variance of the
    Laplacian); ``novel_views_against_input``: with sharp ground truth only, the novel views scored against the
    (blurred) input frames instead."""

    novel_views: ViewScores
    mapping_views: ViewScores
    novel_views_exported: ExportedViewScores
    scored_against: ScoredAgainst
    novel_views_sharper_half: ViewScores
    novel_views_against_input: ViewScores | None = dataclasses.field(default=None, metadata=OMITTED_WHEN_NONE)


@dataclasses.dataclass(kw_only=True)
class ViewPoseErrors:
    """ATE RMSE (m, SE(3)-aligned) of the mapping views' poses: as the frontend gave them, and after the bridge."""

    frontend: float
    rendering: float


@dataclasses.dataclass(kw_only=True)
class BridgeMetrics:
    """The Fusion Bridge: view selections by outcome name, views refined, their mean joint loss before and after
    refinement (None when none was refined); ``views_ate_rmse_m`` only with ground truth and 3 views or more;
    blur-aware mapping's exposure time (s, 0: off), the views rendered at more than one pose over their exposure
    at the mapping resolution and their mean count of poses (None when none)."""

    enabled: bool
    view_selection: dict[str, int]
    refined_views: int
    mean_loss_initial: float | None
    mean_loss_final: float | None
    blur_exposure_s: float = 0.0
    blurred_views: int = 0
    mean_subposes_blurred: float | None = None
    views_ate_rmse_m: ViewPoseErrors | None = dataclasses.field(default=None, metadata=OMITTED_WHEN_NONE)


@dataclasses.dataclass(kw_only=True)
class MapMetrics:
    """What the mapping stage adds: rendering scores, the Gaussian count, the mapping views and their resolution
    ``[width, height]`` (px), the bridge's figures."""

    rendering: RenderingMetrics
    gaussians: int
    mapping_views: int
    mapping_resolution: list[int]
    bridge: BridgeMetrics


@dataclasses.dataclass(kw_only=True)
class DeviceMetrics:
    """Where the mapping stage ran (``cpu`` with the mapper off); on CUDA also the GPU, the torch, CUDA and gsplat
    versions and the peak GPU memory allocated (MB), as :func:`~tambridge.device.device_summary` gives them."""

    device: str
    gpu: str | None = dataclasses.field(default=None, metadata=OMITTED_WHEN_NONE)
    torch_version: str | None = dataclasses.field(default=None, metadata=OMITTED_WHEN_NONE)
    cuda_version: str | None = dataclasses.field(default=None, metadata=OMITTED_WHEN_NONE)
    gsplat_version: str | None = dataclasses.field(default=None, metadata=OMITTED_WHEN_NONE)
    peak_gpu_memory_mb: float | None = dataclasses.field(default=None, metadata=OMITTED_WHEN_NONE)


@dataclasses.dataclass(kw_only=True)
class WorldMetrics:
    """The world of the exported files (:mod:`tambridge.export.world`): ``frame`` (export.world), ``up_source``
    (accelerometer, floor_plane, wall_planes or first_camera) and ``upright_from_first_camera`` (4 rows of 4), the
    rotation applied to every exported pose and point."""

    frame: str
    up_source: str
    upright_from_first_camera: list[list[float]]


@dataclasses.dataclass(kw_only=True)
class RunMetrics:
    """A finished run's figures (``metrics.json``).

    ``sequence``: the folder given; ``frames``, ``keyframes``: counts; ``frontend``: its kind; the ``frames_*``,
    ``loops_closed`` and ``keyframes_culled`` counts come from the frontend (``frames_without_depth``, frames whose
    depth image holds no valid pixel, from the run); ``colour_images_without_depth``: the colour images of rgb.txt
    left out for want of a depth image within 20 ms (all of rgb.txt, before stride and max_frames). Seconds:
    ``frontend_seconds_per_stage`` inside the frontend, ``seconds_per_stage`` of the run (with the evaluation),
    ``seconds_total`` end to end (without the evaluation), ``fps_*`` frames over those seconds (per stage: the stages
    before the evaluation). Memory: peak resident MiB at the end and after tracking.
    ``warnings``: how many the run logged. ``trajectory``: None without ground truth or where it could not be
    compared, ``trajectory_unavailable`` then says why (None with a trajectory); ``map``: None with the mapper off.
    ``world``: the frame of the exported files (None only in metrics not made by a run). ``sequence_fingerprint``:
    what identifies the frames the run read (:func:`~tambridge.checkpoint.sequence_fingerprint`), which
    ``tambridge export`` checks the folder against (None only in metrics not made by a run).
    """

    sequence: str
    frames: int
    keyframes: int
    frontend: str
    frames_lost: int
    frames_relocalised: int
    frames_tracked_by_depth: int = 0
    frames_without_depth: int
    colour_images_without_depth: int = 0
    loops_closed: int
    keyframes_culled: int
    frontend_seconds_per_stage: dict[str, float]
    seconds_total: float
    fps_end_to_end: float
    seconds_per_stage: dict[str, float]
    fps_per_stage: dict[str, float]
    peak_memory_mb: float
    peak_memory_mb_tracking: float
    warnings: int
    trajectory: TrajectoryMetrics | None
    trajectory_unavailable: str | None
    map: MapMetrics | None = dataclasses.field(default=None, metadata=IN_PARENT)
    device: DeviceMetrics = dataclasses.field(metadata=IN_PARENT)
    world: WorldMetrics | None = dataclasses.field(default=None, metadata=OMITTED_WHEN_NONE)
    sequence_fingerprint: dict | None = dataclasses.field(default=None, metadata=OMITTED_WHEN_NONE)


def metrics_json(metrics: RunMetrics) -> dict:
    """The object written to metrics.json: ``schema_version``, then the metrics' keys."""
    return {"schema_version": SCHEMA_VERSION, **_to_json(metrics)}


def write_metrics(path: Path, metrics: RunMetrics) -> None:
    """Write ``metrics`` to ``path`` (atomically)."""
    atomic_write_text(Path(path), json.dumps(metrics_json(metrics), indent=2) + "\n")


def read_metrics(path: Path) -> RunMetrics:
    """The metrics in ``path``; a one-line :class:`TambridgeError` naming it when it is missing, not JSON, of
    another schema version, or lacks or has other keys than :class:`RunMetrics`."""
    path = Path(path)
    if not path.is_file():
        raise TambridgeError(f"{path}: not found; is {path.parent} the output folder of a finished reconstruct run?")
    try:
        data = json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as error:
        raise TambridgeError(f"{path}: not JSON ({error}); not the metrics.json of a reconstruct run") from None
    if not isinstance(data, dict):
        raise TambridgeError(f"{path}: not a JSON object; not the metrics.json of a reconstruct run")
    version = data.pop("schema_version", None)
    if version != SCHEMA_VERSION:
        found = "no schema_version (an older tambridge)" if version is None else f"schema_version {version!r}"
        raise TambridgeError(f"{path}: {found}; this tambridge reads schema_version {SCHEMA_VERSION}: run reconstruct "
                             f"again to rewrite it")
    try:
        return _from_json(RunMetrics, data, "")
    except ValueError as error:
        raise TambridgeError(f"{path}: {error}; not the metrics.json of this tambridge's reconstruct (schema_version "
                             f"{SCHEMA_VERSION})") from None


def _to_json(metrics: object) -> dict:
    data = {}
    for field in dataclasses.fields(metrics):
        value = getattr(metrics, field.name)
        if field.metadata.get("in_parent"):
            data.update({} if value is None else _to_json(value))
        elif value is not None or not field.metadata.get("omitted_when_none"):
            data[field.name] = _to_json(value) if dataclasses.is_dataclass(value) else value
    return data


def _from_json(cls: type, data: dict, where: str) -> object:
    """``cls`` from its JSON object ``data`` (at dotted key ``where``); ValueError naming the key that is wrong."""
    if not isinstance(data, dict):
        raise ValueError(f"{where} is not an object")
    values, used = {}, set()
    for field, kind in _fields(cls):
        key = f"{where}.{field.name}" if where else field.name
        if field.metadata.get("in_parent"):
            keys = {inner.name for inner in dataclasses.fields(kind)}
            if field.default is None and not keys & data.keys():
                continue
            values[field.name] = _from_json(kind, {k: v for k, v in data.items() if k in keys}, where)
            used |= keys
        elif field.name in data:
            value = data[field.name]
            values[field.name] = _from_json(kind, value, key) if kind is not None and value is not None else value
            used.add(field.name)
        elif field.default is dataclasses.MISSING:
            raise ValueError(f"lacks key {key!r}")
    unknown = sorted(data.keys() - used)
    if unknown:
        raise ValueError(f"unknown key {(f'{where}.' if where else '') + unknown[0]!r}")
    return cls(**values)


def _fields(cls: type) -> list[tuple[dataclasses.Field, type | None]]:
    """Each field of dataclass ``cls`` with the dataclass its value is (``X | None`` too), else None."""
    hints = typing.get_type_hints(cls)
    result = []
    for field in dataclasses.fields(cls):
        kinds = [hints[field.name], *typing.get_args(hints[field.name])]
        result.append((field, next((kind for kind in kinds if dataclasses.is_dataclass(kind)), None)))
    return result
