"""Config resolution and what each key accepts: defaults <- preset <- overrides, the choices and ranges refused at
load time, the ``config`` command, config.yaml round trip and the values a run on a given camera uses."""

import dataclasses
import math
from pathlib import Path

import pytest
import torch
import yaml
from click.testing import CliRunner

from cli import main
from tambridge.camera import Camera, load_sensor_file
from tambridge.config import (Config, check_config, config_for_camera, config_keys, describe_config, load_config,
                              to_dict, to_yaml)
from tambridge.device import resolve_device
from tambridge.errors import ConfigError
from tambridge.export.config import MeshSource
from tambridge.frontend.config import FrontendKind
from tambridge.frontend.orb.config import scaled_for_image
from tambridge.settings import Choice, Device

ROOT = Path(__file__).resolve().parents[1]
KEYS = {key: (field, annotation) for key, _, field, annotation in config_keys(Config())}


def _kind(annotation):
    """The type of a key, without ``| None`` (and for ``device``, without ``| str``)."""
    args = [a for a in getattr(annotation, "__args__", (annotation,)) if a is not type(None)]
    return args[0]


CHOICE_KEYS = [key for key, (_, annotation) in KEYS.items() if issubclass(_kind(annotation), Choice)]
FLOAT_KEYS = [key for key, (_, annotation) in KEYS.items() if _kind(annotation) is float]
RANGED_KEYS = [key for key, (field, _) in KEYS.items() if field.metadata.get("accepts") is not None]
COMPANIONS = {"mesh.truncation_m": ["mesh.voxel_size_m=1e-9"], "frontend.orb.max_depth_m": ["frontend.orb.min_depth_m=0"]}
"""Overrides that keep a rule between keys out of the way when one key is set to the edge of its range."""


def test_nested_frontend_settings_reachable_from_overrides():
    config = load_config(None, ["frontend.orb.n_features=2000", "frontend.orb.mapping_thread=false",
                                "frontend.open3d.max_depth_m=3.5"])
    assert config.frontend.orb.n_features == 2000
    assert config.frontend.orb.mapping_thread is False
    assert config.frontend.open3d.max_depth_m == 3.5


@pytest.mark.parametrize("override, message", [
    ("frontend.orb.no_such_key=1", "frontend.orb.no_such_key"),
    ("frontend.orb.n_features=many", "frontend.orb.n_features"),
    ("mapper.iterations", "expected key=value"),
    ("mapper.iterations=true", "mapper.iterations: expected int"),
])
def test_bad_overrides_name_the_key(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(None, [override])


@pytest.mark.parametrize("preset", sorted((ROOT / "configs").glob("*.yaml")), ids=lambda path: path.name)
def test_every_preset_loads(preset):
    config = load_config(preset)
    # The default preset is the defaults themselves; every other one changes something.
    assert (config == Config()) == (preset.name == "default.yaml")


def test_the_presets_say_what_they_change():
    assert load_config(ROOT / "configs" / "open3d.yaml").frontend.kind is FrontendKind.open3d
    fast, quality = load_config(ROOT / "configs" / "fast.yaml"), load_config(ROOT / "configs" / "quality.yaml")
    assert fast.mapper.resolution_scale == 0.125 < Config().mapper.resolution_scale == quality.mapper.resolution_scale
    assert Config().mapper.iterations < quality.mapper.iterations == 40
    assert quality.mesh.voxel_size_m == 0.01 < Config().mesh.voxel_size_m
    assert Config().mapper.sharp_iterations_per_view == 2 < quality.mapper.sharp_iterations_per_view == 4


def test_a_key_given_twice_or_a_bad_value_in_a_preset_names_the_file(tmp_path):
    (tmp_path / "twice.yaml").write_text("mapper:\n  iterations: 5\n  iterations: 7\n")
    (tmp_path / "bad.yaml").write_text("mapper:\n  iterations: x\n")
    for name, message in (("twice.yaml", "not valid YAML (key 'iterations' is given twice at line 3, column 3)"),
                          ("bad.yaml", "mapper.iterations: expected int, got 'x'")):
        with pytest.raises(ConfigError) as refused:
            load_config(tmp_path / name)
        assert str(refused.value).startswith(f"{tmp_path / name}: {message}")


def test_yaml_merge_keys_and_complex_keys_load_as_before(tmp_path):
    from tambridge.files import load_yaml

    # A merge key brings keys in that the mapping may override: not a key given twice.
    text = "base: &base {iterations: 5, enabled: true}\nmapper:\n  <<: *base\n  iterations: 7\n"
    assert load_yaml(text)["mapper"] == {"iterations": 7, "enabled": True}
    with pytest.raises(yaml.YAMLError):
        load_yaml("? [a, b]\n: 1\n")  # as yaml.safe_load refuses it: an unhashable key, not a traceback


def test_a_preset_that_is_not_utf8_is_refused_naming_it(tmp_path):
    (tmp_path / "latin1.yaml").write_bytes("mapper:\n  iterations: 5 # caf\u00e9\n".encode("latin-1"))
    (tmp_path / "utf16.yaml").write_bytes("mapper:\n  iterations: 5\n".encode("utf-16"))
    for name, message in (("latin1.yaml", "is not UTF-8 text (byte 0xe9 at offset 29); save it as UTF-8"),
                          ("utf16.yaml", "is UTF-16 text; save it as UTF-8")):
        with pytest.raises(ConfigError) as refused:
            load_config(tmp_path / name)
        assert str(refused.value).startswith(f"{tmp_path / name}: {message}")


def test_presets_and_camera_files_are_found_by_name_from_any_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # outside the checkout, as a user runs the README's commands
    for given in ("fast", "fast.yaml", "configs/fast.yaml"):
        assert load_config(given) == load_config(ROOT / "configs" / "fast.yaml")
    kinect = str(ROOT / "configs" / "cameras" / "7scenes_kinect.yaml")
    for given in ("7scenes_kinect", "configs/cameras/7scenes_kinect.yaml"):
        assert load_config(overrides=[f"input.camera_file={given}"]).input.camera_file == kinect
    # A file of the user's comes first, under whatever name.
    (tmp_path / "fast.yaml").write_text("mapper:\n  iterations: 7\n")
    assert load_config("fast.yaml").mapper.iterations == 7
    with pytest.raises(ConfigError) as missing:
        load_config("fastest")
    assert str(missing.value) == (f"fastest: config file not found; give a YAML file, or a preset's name (default, "
                                  f"fast, long, open3d, quality in {ROOT / 'configs'})")
    assert load_config(overrides=["input.camera_file=mine.yaml"]).input.camera_file == "mine.yaml"


@pytest.mark.parametrize("camera_file", sorted((ROOT / "configs" / "cameras").glob("*.yaml")), ids=lambda path: path.name)
def test_every_camera_file_loads(camera_file):
    # Camera files are not run configs: they go to --camera and are read by tambridge.camera.
    values, sensor = yaml.safe_load(camera_file.read_text()), load_sensor_file(camera_file)
    assert (sensor.camera.width, sensor.camera.height, sensor.camera.fx) == (values["width"], values["height"], values["fx"])
    assert sensor.depth_scale == values["depth_scale"]


def test_every_key_has_a_doc_line_and_every_number_a_range():
    for key, (field, annotation) in KEYS.items():
        doc = field.metadata.get("doc", "")
        assert doc and "\n" not in doc, key
        if _kind(annotation) in (int, float):
            assert field.metadata.get("accepts") is not None, f"{key} has no range"
    assert len(KEYS) > 100


def test_the_defaults_are_accepted():
    assert check_config(Config()) == Config()


@pytest.mark.parametrize("key", CHOICE_KEYS)
def test_each_choice_refuses_a_bad_value_naming_the_allowed_ones(key):
    choice = _kind(KEYS[key][1])
    with pytest.raises(ConfigError) as raised:
        load_config(None, [f"{key}=no_such_value"])
    message = str(raised.value)
    assert message.startswith(f"{key}='no_such_value': expected one of") and "\n" not in message
    assert all(member.value in message for member in choice)
    for member in choice:
        assert dict(config_values(load_config(None, [f"{key}={member.value.upper()}"])))[key] is member


def config_values(config):
    return ((key, getattr(owner, field.name)) for key, owner, field, _ in config_keys(config))


def test_choices_compare_hash_and_print_as_their_strings():
    assert FrontendKind.open3d_f2f == "open3d_f2f" and {"orb": 1}[FrontendKind.orb] == 1
    assert f"{MeshSource.rendered}" == str(MeshSource.rendered) == "rendered"
    assert [kind.value for kind in FrontendKind] == ["orb", "open3d", "open3d_f2f"]


def test_a_renamed_mesh_source_says_its_new_name():
    for old, new in (("tsdf", "sensor"), ("gaussians", "rendered")):
        with pytest.raises(ConfigError, match=f"mesh.source='{old}'.*{old} is now called {new}"):
            load_config(None, [f"mesh.source={old}"])


def test_device_takes_its_choices_and_cuda_n():
    assert load_config(None, ["device=AUTO"]).device is Device.auto
    assert load_config(None, ["device=cuda:1"]).device == "cuda:1"
    for bad in ("gpu", "cuda:", "cuda:x", ""):
        with pytest.raises(ConfigError, match="device=.*expected one of auto, cpu, cuda"):
            load_config(None, [f"device={bad}"])
    assert resolve_device(Device.cpu) == torch.device("cpu")


def _step(kind, bound: float) -> float:
    """The smallest change that crosses a range's bound for an int or float key."""
    return 1 if kind is int else 1e-6 * max(1.0, abs(bound))


@pytest.mark.parametrize("key", RANGED_KEYS)
def test_each_range_refuses_a_value_past_it_and_accepts_its_edge(key):
    field, annotation = KEYS[key]
    accepts, kind = field.metadata["accepts"], _kind(annotation)
    edges = []  # (value, accepted)
    for bound, is_open, direction in ((accepts.low, accepts.low_open, -1), (accepts.high, accepts.high_open, +1)):
        if bound is None:
            continue
        step = _step(kind, bound)
        edges += [(bound, not is_open), (bound + direction * step, False), (bound - direction * step, True)]
    assert edges, key
    for value, accepted in edges:
        value = kind(value) if kind is int else value
        overrides = COMPANIONS.get(key, []) + [f"{key}={value!r}"]
        if accepted:
            assert dict(config_values(load_config(None, overrides)))[key] == value, (key, value)
        else:
            with pytest.raises(ConfigError) as raised:
                load_config(None, overrides)
            message = str(raised.value)
            assert message.startswith(f"{key}=") and f"must be {accepts}" in message and "\n" not in message


@pytest.mark.parametrize("key, refused, accepted", [
    ("mapper.resolution_scale", 0, 1), ("mapper.resolution_scale", 1.01, 0.01), ("evaluation.novel_view_every", 0, 1),
    ("mapper.lr_means_m", 0, 1e-9), ("mapper.lr_exposure", -1e-3, 1e-3), ("frontend.orb.n_features", 0, 1),
    ("mapper.iterations", -1, 0), ("bridge.alpha", 0, 1), ("bridge.beta", -1, 0), ("bridge.gamma", 0, 1),
    ("mapper.window_size", 0, 1), ("input.stride", 0, 1), ("input.max_frames", 0, 1), ("checkpoint.every_keyframes", -1, 0),
    ("mesh.voxel_size_m", 0, 0.001), ("frontend.open3d.loop_voxel_m", 0, 0.001), ("seed", -1, 0),
])
def test_the_ranges_are_those_meant(key, refused, accepted):
    with pytest.raises(ConfigError, match=f"{key}={refused!r}"):
        load_config(None, [f"{key}={refused}"])
    assert dict(config_values(load_config(None, [f"{key}={accepted}"])))[key] == accepted


@pytest.mark.parametrize("key", FLOAT_KEYS)
@pytest.mark.parametrize("value", ["nan", ".inf", "-.inf", "-inf"])
def test_every_float_key_refuses_nan_and_inf(key, value):
    with pytest.raises(ConfigError, match=f"{key}=.*expected a finite number"):
        load_config(None, [f"{key}={value}"])


def test_nan_in_a_preset_is_refused_with_the_key(tmp_path):
    preset = tmp_path / "p.yaml"
    preset.write_text("bridge:\n  gamma: .nan\n")
    with pytest.raises(ConfigError, match="bridge.gamma=nan: expected a finite number"):
        load_config(preset)


@pytest.mark.parametrize("overrides, message", [
    (["mesh.truncation_m=0.02"], "mesh: truncation_m=0.02 must be larger than voxel_size_m=0.02"),
    (["frontend.orb.min_depth_m=9"], "frontend.orb: min_depth_m=9 must be below max_depth_m=8"),
])
def test_rules_between_keys_are_checked_at_load(overrides, message):
    with pytest.raises(ConfigError, match=message):
        load_config(None, overrides)


def test_a_later_override_may_repair_an_earlier_value(tmp_path):
    preset = tmp_path / "p.yaml"
    preset.write_text("mapper:\n  resolution_scale: 2.0\n")
    assert load_config(preset, ["mapper.resolution_scale=0.5"]).mapper.resolution_scale == 0.5


def test_values_set_in_code_are_checked_and_typed():
    config = Config()
    config.frontend.kind = "open3d"
    config.mapper.iterations = 3.0
    assert check_config(config).frontend.kind is FrontendKind.open3d and type(config.mapper.iterations) is int
    config.bridge.alpha = 0.0
    with pytest.raises(ConfigError, match=r"bridge.alpha=0.0: must be in \(0, 1\]"):
        check_config(config)


def test_written_config_loads_back_identically_as_plain_yaml(tmp_path):
    config = load_config(None, ["frontend.kind=open3d", "mapper.iterations=7", "frontend.orb.vocabulary_path=/x.npz",
                                "mesh.source=rendered", "mapper.backend=reference", "device=cuda:1"])
    text = to_yaml(config)
    assert "!!" not in text and "  kind: open3d\n" in text and "  source: rendered\n" in text
    plain = to_dict(config)
    assert type(plain["frontend"]["kind"]) is str and type(plain["device"]) is str
    path = tmp_path / "config.yaml"
    path.write_text(text)
    assert load_config(path) == config
    assert load_config(path).frontend.kind is FrontendKind.open3d


def test_config_command_lists_every_key_with_its_doc():
    result = CliRunner().invoke(main, ["config", "--config", str(ROOT / "configs" / "fast.yaml"), "--set",
                                       "mapper.iterations=7", "--set", "device=auto"])
    assert result.exit_code == 0, result.output
    lines = result.output.strip().splitlines()
    parsed = {}
    for line in lines:
        assignment, doc = line.split("  # ", 1)
        key, value = assignment.split(" = ", 1)
        parsed[key] = value
        assert doc.strip(), line
    assert list(parsed) == list(KEYS)
    assert parsed["mapper.iterations"] == "7" and parsed["mapper.resolution_scale"] == "0.125"
    assert parsed["device"] == "auto" and parsed["input.max_frames"] == "null" and parsed["bridge.enabled"] == "true"
    assert "in (0, 1]" in dict(zip(KEYS, lines))["mapper.resolution_scale"]
    assert lines == describe_config(load_config(ROOT / "configs" / "fast.yaml", ["mapper.iterations=7", "device=auto"]))
    # Each printed value, given back as --set, gives the same config.
    again = load_config(None, [f"{key}={value}" for key, value in parsed.items()])
    assert again == load_config(ROOT / "configs" / "fast.yaml", ["mapper.iterations=7", "device=auto"])


def test_config_command_refuses_a_bad_value_in_one_line():
    result = CliRunner().invoke(main, ["config", "--set", "evaluation.novel_view_every=0"])
    assert result.exit_code == 2
    assert result.output.strip() == "error: evaluation.novel_view_every=0: must be >= 1"


def test_cli_choices_come_from_the_enums():
    result = CliRunner().invoke(main, ["reconstruct", "--help"])
    assert "[sensor|rendered]" in result.output and "[auto|cpu|cuda]" in result.output
    result = CliRunner().invoke(main, ["reconstruct", "x", "-o", "y", "--mesh-from", "tsdf"])
    assert result.exit_code == 2 and "'tsdf' is not one of 'sensor', 'rendered'" in result.output


@pytest.mark.parametrize("width, height", [(160, 120), (320, 240), (1280, 960)])
def test_config_for_camera_records_the_values_the_frontend_uses(width, height):
    config = load_config(None, ["frontend.orb.n_features=1200"])
    before = to_dict(config)
    camera = Camera(width, height, 500.0, 500.0, width / 2, height / 2)
    effective = config_for_camera(config, camera)
    assert to_dict(config) == before, "the given config is left as it was"
    scaled = scaled_for_image(config.frontend.orb, width, height)
    assert effective.frontend.orb == dataclasses.replace(scaled, scale_with_image=False, rolling_shutter_s=0.0)
    assert effective.frontend.orb.n_features == round(1200 * math.sqrt(math.sqrt(width * height / (640 * 480))))
    # The frontend, given the recorded values, adapts nothing more; config.yaml loaded again is the same run.
    assert scaled_for_image(effective.frontend.orb, width, height) == effective.frontend.orb
    reloaded = check_config(load_config(None, [f"{key}={value}" for key, value in config_values(effective)
                                               if value is not None]))
    assert config_for_camera(reloaded, camera) == reloaded == effective
    assert dataclasses.replace(effective, frontend=config.frontend) == config


def test_config_for_camera_at_the_reference_size_changes_only_the_flag():
    camera = Camera(640, 480, 500.0, 500.0, 320.0, 240.0)
    effective = config_for_camera(Config(), camera)
    assert effective.frontend.orb == dataclasses.replace(Config().frontend.orb, scale_with_image=False, rolling_shutter_s=0.0)
    small = config_for_camera(Config(), Camera(160, 120, 125.0, 125.0, 80.0, 60.0)).frontend.orb
    assert (small.n_features, small.n_levels, small.edge_threshold_px, small.grid_cell_px) == (750, 4, 10, 16)


def test_config_for_camera_records_the_cameras_rolling_shutter():
    kinect = Camera(640, 480, 517.3, 516.5, 318.6, 255.3, rolling_shutter_s=0.015)
    assert config_for_camera(Config(), kinect).frontend.orb.rolling_shutter_s == 0.015
    given = load_config(None, ["frontend.orb.rolling_shutter_s=0"])
    assert config_for_camera(given, kinect).frontend.orb.rolling_shutter_s == 0.0
