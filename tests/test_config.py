"""Config resolution: defaults <- preset <- overrides, nested frontend settings, config.yaml round trip."""

import pytest

from tambridge.config import load_config, to_yaml
from tambridge.errors import ConfigError


def test_nested_frontend_settings_reachable_from_overrides():
    config = load_config(None, ["frontend.orb.n_features=2000", "frontend.orb.mapping_thread=false",
                                "frontend.open3d.max_depth_m=3.5"])
    assert config.frontend.orb.n_features == 2000
    assert config.frontend.orb.mapping_thread is False
    assert config.frontend.open3d.max_depth_m == 3.5


def test_written_config_loads_back_identically(tmp_path):
    config = load_config(None, ["frontend.kind=open3d", "mapper.iterations=7", "frontend.orb.vocabulary_path=/x.npz"])
    path = tmp_path / "config.yaml"
    path.write_text(to_yaml(config))
    assert load_config(path) == config


@pytest.mark.parametrize("override, message", [
    ("frontend.orb.no_such_key=1", "frontend.orb.no_such_key"),
    ("frontend.orb.n_features=many", "frontend.orb.n_features"),
    ("mapper.iterations", "expected key=value"),
])
def test_bad_overrides_name_the_key(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(None, [override])
