"""Run configuration: dataclasses whose defaults are the paper's values; YAML presets and ``--set`` only override.

A config is resolved once (defaults <- preset YAML <- ``key.sub=value`` overrides), checked against what every key
accepts (:mod:`tambridge.settings`) before any frame is read, and written next to the results as ``config.yaml``
with the values the run used (:func:`config_for_camera`), so every run can be repeated from its output folder.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import types
import typing
from pathlib import Path

import yaml

from tambridge.errors import ConfigError
from tambridge.files import config_file_names, find_config_file, load_yaml, read_text_file, yaml_error_line
from tambridge.bridge.config import BridgeConfig
from tambridge.checkpoint import CheckpointConfig
from tambridge.evaluation.config import EvaluationConfig
from tambridge.export.config import ExportConfig, MeshConfig
from tambridge.frontend.config import FrontendConfig
from tambridge.frontend.orb.config import for_camera
from tambridge.gaussians.config import MapperConfig
from tambridge.io.config import InputConfig
from tambridge.settings import NON_NEGATIVE, Choice, Device, section, setting

if typing.TYPE_CHECKING:
    from tambridge.camera import Camera


@dataclasses.dataclass
class Config:
    """The whole run configuration."""

    input: InputConfig = section(InputConfig, "which frames of the sequence are read")
    frontend: FrontendConfig = section(FrontendConfig, "the tracking frontend")
    bridge: BridgeConfig = section(BridgeConfig, "the Fusion Bridge: view selection and pose refinement")
    mapper: MapperConfig = section(MapperConfig, "the online Gaussian mapper")
    mesh: MeshConfig = section(MeshConfig, "the TSDF mesh")
    export: ExportConfig = section(ExportConfig, "the world frame of the exported files")
    evaluation: EvaluationConfig = section(EvaluationConfig, "the rendering evaluation")
    seed: int = setting(0, "seed of the mapping stage's random choices", NON_NEGATIVE)
    checkpoint: CheckpointConfig = section(CheckpointConfig, "checkpoints for reconstruct --resume")
    # cpu is the path that ships and is tested; resolved once per run by tambridge.device.resolve_device.
    device: Device | str = setting(Device.cpu, "torch device of the Gaussian map, the bridge and the rendering "
                                               "evaluation: cpu, cuda (needs gsplat), cuda:N or auto")


def to_dict(config: Config) -> dict:
    """``config`` as plain YAML/JSON values (a choice as its string)."""
    plain = lambda items: {key: value.value if isinstance(value, enum.Enum) else value for key, value in items}  # noqa: E731
    return dataclasses.asdict(config, dict_factory=plain)


def to_yaml(config: Config) -> str:
    return yaml.safe_dump(to_dict(config), sort_keys=False)


def config_keys(config) -> typing.Iterator[tuple[str, object, dataclasses.Field, typing.Any]]:
    """Every key of ``config`` in declaration order, sections depth first: (dotted key, the dataclass holding it,
    its field, its type)."""
    hints = typing.get_type_hints(type(config))
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        if dataclasses.is_dataclass(value):
            for key, owner, inner, annotation in config_keys(value):
                yield f"{field.name}.{key}", owner, inner, annotation
        else:
            yield field.name, config, field, hints[field.name]


def _sections(config, prefix: str = "") -> typing.Iterator[tuple[str, object]]:
    """``config`` and every nested section: (dotted name, the dataclass)."""
    yield prefix, config
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        if dataclasses.is_dataclass(value):
            yield from _sections(value, f"{prefix}{field.name}.")


def _optional(annotation) -> tuple[typing.Any, bool]:
    """(the type, whether None is accepted) of ``X``, ``X | None`` or ``X | str`` (the first type given counts)."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        options = typing.get_args(annotation)
        return [a for a in options if a is not type(None)][0], type(None) in options
    return annotation, False


def _coerce(value, annotation, key: str):
    """``value`` (from YAML, ``--set`` or code) as the key's type: bool, int, float (finite), str, a Choice, or
    optional of those; ConfigError naming the key otherwise."""
    kind, optional = _optional(annotation)
    if optional and (value is None or (isinstance(value, str) and value.strip().lower() in ("null", "none"))):
        return None
    if isinstance(kind, type) and issubclass(kind, Choice):
        parsed = kind.parse(value)
        if parsed is None:
            renamed = kind.renamed().get(str(value).strip().lower())
            hint = f" ({value} is now called {renamed})" if renamed else ""
            raise ConfigError(f"{key}={value!r}: expected {kind.accepted()}{hint}")
        return parsed
    if kind is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false", "on", "off", "yes", "no", "1", "0"):
            return value.lower() in ("true", "on", "yes", "1")
        raise ConfigError(f"{key}: expected true/false, got {value!r}")
    try:
        if kind is int:
            if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
                raise ValueError
            return int(value)
        if kind is float:
            if isinstance(value, bool):
                raise ValueError
            number = float(value)
            if not math.isfinite(number):
                raise ConfigError(f"{key}={value!r}: expected a finite number")
            return number
        if kind is str:
            return str(value)
    except (TypeError, ValueError, OverflowError):
        raise ConfigError(f"{key}: expected {kind.__name__}, got {value!r}") from None
    raise ConfigError(f"{key}: unsupported field type {annotation}")


def _accepts(field: dataclasses.Field, annotation) -> str:
    """What a key accepts, in words ("" for a plain bool or str)."""
    kind, optional = _optional(annotation)
    accepts = field.metadata.get("accepts")
    words = kind.accepted() if isinstance(kind, type) and issubclass(kind, Choice) else str(accepts or "")
    return f"null or {words}" if optional and words else words


def check_config(config: Config) -> Config:
    """Refuse a value that its key does not accept: a one-line ConfigError naming the key, the value and what is
    accepted. Values given as strings or ints in code become the keys' types (in place). Returns ``config``."""
    for key, owner, field, annotation in config_keys(config):
        value = _coerce(getattr(owner, field.name), annotation, key)
        accepts = field.metadata.get("accepts")
        if accepts is not None and value is not None and value not in accepts:
            raise ConfigError(f"{key}={value!r}: must be {accepts}")
        setattr(owner, field.name, value)
    for prefix, settings in _sections(config):
        conflict = getattr(settings, "conflict", None)
        message = conflict() if conflict is not None else None
        if message:
            raise ConfigError(f"{prefix.rstrip('.')}: {message}")
    return config


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
    """Defaults, then a YAML preset, then ``section.key=value`` overrides (values parsed as YAML scalars), then
    :func:`check_config`."""
    config = Config()
    if preset is not None:
        given, preset = preset, find_config_file(preset)
        if not preset.is_file():
            raise ConfigError(f"{given}: config file not found; give a YAML file, or a preset's name "
                              f"({config_file_names()})")
        try:
            values = load_yaml(read_text_file(preset, ConfigError)) or {}
        except yaml.YAMLError as error:
            raise ConfigError(f"{preset}: not valid YAML ({yaml_error_line(error)})") from error
        if not isinstance(values, dict):
            raise ConfigError(f"{preset}: expected a mapping at the top level")
        try:
            _apply(config, values, "")
        except ConfigError as error:
            raise ConfigError(f"{preset}: {error}") from None
    for override in overrides:
        if "=" not in override:
            raise ConfigError(f"--set {override!r}: expected key=value, e.g. --set mapper.iterations=50")
        key, raw = override.split("=", 1)
        nested: dict = {}
        cursor = nested
        parts = key.strip().split(".")
        for part in parts[:-1]:
            cursor = cursor.setdefault(part, {})
        try:
            cursor[parts[-1]] = yaml.safe_load(raw) if raw.strip() else None
        except yaml.YAMLError as error:
            raise ConfigError(f"--set {override!r}: the value is not valid YAML ({yaml_error_line(error)}); give a "
                              "number, true/false, null or a quoted string") from None
        _apply(config, nested, "")
    if config.input.camera_file is not None:
        # The file the run reads, recorded as such in its config.yaml.
        config.input.camera_file = str(find_config_file(Path(config.input.camera_file), "cameras"))
    return check_config(config)


def _scalar(value) -> str:
    """A value as it is written in YAML and ``--set``."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def describe_config(config: Config) -> list[str]:
    """One line per key: ``key = value  # documentation; what it accepts``."""
    lines = []
    for key, owner, field, annotation in config_keys(config):
        accepts = _accepts(field, annotation)
        lines.append(f"{key} = {_scalar(getattr(owner, field.name))}  # {field.metadata.get('doc', '')}"
                     + (f"; {accepts}" if accepts else ""))
    return lines


def config_for_camera(config: Config, camera: "Camera") -> Config:
    """``config`` with the values a run on ``camera`` uses: the ORB settings adapted to its image size and
    rolling-shutter readout by :func:`~tambridge.frontend.orb.config.for_camera`, with ``scale_with_image`` off so
    that these values, written to config.yaml and loaded again, give the same run. ``config`` itself is not
    changed."""
    orb = dataclasses.replace(for_camera(config.frontend.orb, camera), scale_with_image=False)
    return dataclasses.replace(config, frontend=dataclasses.replace(config.frontend, orb=orb))
