"""The viewer's web server (apps/viewer/app): its address, the loopback rule, allowed hosts."""

from __future__ import annotations

import pytest

from sogm_service.apps.viewer import allowed_hosts, is_loopback, main, parse_http


def test_http_address_parsing_and_the_loopback_rule() -> None:
    assert parse_http("127.0.0.1:8080") == ("127.0.0.1", 8080)
    assert parse_http("[::1]:0") == ("::1", 0)
    assert parse_http(":9000") == ("127.0.0.1", 9000)
    for bad in ("8080", "host:", "host:99999", "host:http"):
        with pytest.raises(ValueError):
            parse_http(bad)
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.0.2.1")
    assert "0.0.0.0" not in allowed_hosts("0.0.0.0", [])
    assert "viewer.example" in allowed_hosts("127.0.0.1", ["viewer.example"])


def test_view_refuses_to_listen_beyond_loopback_without_being_told(
        capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--http", "0.0.0.0:8080"]) == 2
    err = capsys.readouterr().err
    assert "refusing to listen on 0.0.0.0" in err and "ssh -L" in err
    assert main(["--http", "nonsense"]) == 2
