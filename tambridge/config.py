"""Run configuration: dataclasses whose defaults are the paper's values; YAML presets and ``--set`` only override.

A config is resolved once (defaults <- preset YAML <- ``key.sub=value`` overrides) and written next to the
results as ``config.yaml``, so every run can be repeated from its output folder.
"""

from __future__ import annotations

import dataclasses
import typing
from pathlib import Path

import yaml

from tambridge.errors import ConfigError
from tambridge.bridge.config import BridgeConfig
from tambridge.checkpoint import CheckpointConfig
from tambridge.evaluation.config import EvaluationConfig
from tambridge.export.config import MeshConfig
from tambridge.frontend.config import FrontendConfig
from tambridge.gaussians.config import MapperConfig
from tambridge.io.config import InputConfig


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
