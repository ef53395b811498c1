"""Configuration: the documented example is the defaults, bad files fail with field + reason."""

from __future__ import annotations

from pathlib import Path

import pytest
import zenoh

from sogm_service.service.config import ConfigError, ServiceConfig, load_config
from sogm_service.service.config_reference import REGENERATE, render_toml
from tests.conftest import write_config

DEPLOY = Path(__file__).resolve().parents[3] / "deploy"


def test_deploy_example_documents_exactly_the_defaults() -> None:
    assert load_config(DEPLOY / "sogm-service.toml") == ServiceConfig()


def test_deploy_example_is_generated_from_the_models() -> None:
    text = (DEPLOY / "sogm-service.toml").read_text(encoding="utf-8")
    assert text == render_toml(), f"deploy/sogm-service.toml is stale: run `{REGENERATE}`"


def test_no_file_means_defaults() -> None:
    cfg = load_config(None)
    assert cfg.map.name == "default" and cfg.ism[0].key_expr == "ism/**"
    assert cfg.zenoh.multicast_scouting is False


@pytest.mark.parametrize(("text", "field", "reason"), [
    ("[map]\ntile_size = 300\n", "map.tile_size", "power of two"),
    ("[map]\nresolution = -1\n", "map.resolution", "greater than 0"),
    ("[limits]\nqueue_policy = \"sometimes\"\n", "limits.queue_policy", "lossless"),
    ("[storage]\nchekpoint_interval_s = 3\n", "storage.chekpoint_interval_s", "Extra"),
    ("[map\n", "", "not valid TOML"),
])
def test_bad_config_names_field_and_reason(tmp_path: Path, text: str, field: str,
                                           reason: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert field in str(err.value) and reason in str(err.value)


@pytest.mark.parametrize("name", ["zenoh-robot-client.json5", "zenoh-robot-peer.json5",
                                  "zenoh-router.json5", "zenoh-server.json5"])
def test_deploy_zenoh_configs_parse(name: str) -> None:
    zenoh.Config.from_file(str(DEPLOY / name))


def test_config_numbers_are_strict(tmp_path: Path) -> None:
    path = write_config(tmp_path / "c.toml", {"map": {"resolution": "0.1"}})
    with pytest.raises(ConfigError, match="resolution"):
        load_config(path)
    ok = write_config(tmp_path / "ok.toml", {"map": {"resolution": 1},
                                            "storage": {"directory": "tiles"}})
    config = load_config(ok)
    assert config.map.resolution == 1.0 and config.storage.directory == Path("tiles")
