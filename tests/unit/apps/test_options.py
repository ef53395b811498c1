"""The shared parts of the command tree: help format, one-line parser errors, overrides."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from sogm_service.apps.options import (
    HelpFormatter,
    MissingExtraError,
    Parser,
    UsageError,
    require_extra,
)
from sogm_service.apps.serve import apply_overrides
from sogm_service.service.config import ServiceConfig


def _help(**kwargs: object) -> str:
    p = Parser(prog="sogm-service x", formatter_class=HelpFormatter)
    p.add_argument("--opt", **kwargs)  # type: ignore[arg-type]
    return " ".join(p.format_help().split())


def test_a_default_is_shown_once() -> None:
    assert "size (m) (default: 0.05)" in _help(type=float, default=0.05, help="size (m)")
    assert "(default: 0)" in _help(type=int, default=0, help="count")  # 0 is a value
    stated = _help(default=None, help="cell size (default: the map's)")
    assert stated.count("default") == 1
    assert "(default: None)" not in _help(default=None, help="layers")
    assert "(default: False)" not in _help(action="store_true", help="a flag")


def test_a_parser_mistake_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    p = Parser(prog="sogm-service tiles ls")
    p.add_argument("--n", type=int)
    with pytest.raises(SystemExit) as done:
        p.parse_args(["--n", "many"])
    assert done.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("sogm-service: tiles ls: argument --n")


def test_require_extra_sees_a_module_set_to_none(monkeypatch: pytest.MonkeyPatch) -> None:
    require_extra("ros2", "export nav2")  # installed here
    monkeypatch.setitem(__import__("sys").modules, "yaml", None)
    with pytest.raises(MissingExtraError, match=r"export nav2 needs the ros2 extra: "
                                                r"pip install 'sogm-service\[ros2\]'"):
        require_extra("ros2", "export nav2")


def _serve_args(**given: object) -> argparse.Namespace:
    base: dict[str, object] = dict(listen=None, connect=None, zenoh_config=None, storage=None,
                                   ros2=None, ros2_domain=None)
    return argparse.Namespace(**{**base, **given})


def test_overrides_replace_only_the_fields_given(tmp_path: Path) -> None:
    config = ServiceConfig.model_validate({"zenoh": {"listen": ["tcp/127.0.0.1:7000"]},
                                           "ros2": {"domain": 5}})
    same = apply_overrides(config, _serve_args())
    assert same.zenoh.listen == ["tcp/127.0.0.1:7000"] and same.ros2.domain == 5
    changed = apply_overrides(config, _serve_args(storage=tmp_path, ros2=True, ros2_domain=0,
                                                  connect=["tcp/127.0.0.1:7001"]))
    assert changed.storage.directory == tmp_path and changed.ros2.enabled
    assert changed.ros2.domain == 0  # 0 is a domain, not "not given"
    assert changed.zenoh.connect == ["tcp/127.0.0.1:7001"]
    assert changed.zenoh.listen == ["tcp/127.0.0.1:7000"]


def test_overrides_listen_where_clients_connect_when_nothing_names_an_endpoint() -> None:
    config = apply_overrides(ServiceConfig(), _serve_args())
    assert config.zenoh.listen == ["tcp/127.0.0.1:7447"]


def test_an_invalid_override_names_its_flag(tmp_path: Path) -> None:
    with pytest.raises(UsageError, match="--ros2-domain"):
        apply_overrides(ServiceConfig(), _serve_args(ros2_domain=999))
    with pytest.raises(UsageError, match="no such file"):
        apply_overrides(ServiceConfig(), _serve_args(zenoh_config=tmp_path / "none.json5"))
