"""The dev PKI of ``sogm-service certs`` (apps/certs): the CA, identities and the Zenoh configs
it writes (direct and router topologies), and the command's init, add, renew and refusals.

Its ``config_dict`` reads a generated config for the secure site's integration tests too."""

from __future__ import annotations

import datetime as dt
import json
import os
import stat
from pathlib import Path
from typing import Any

import pytest
import zenoh
from cryptography import x509
from cryptography.x509.oid import NameOID

from sogm_service.apps import certs
from sogm_service.apps.certs import init_pki


def config_dict(path: Path) -> dict[str, Any]:
    """The JSON body of a generated config (the header is ``//`` comment lines)."""
    body = "\n".join(ln for ln in path.read_text().splitlines() if not ln.startswith("//"))
    d: dict[str, Any] = json.loads(body)
    return d


def test_init_writes_ca_identities_and_configs(tmp_path: Path) -> None:
    pki = init_pki(tmp_path / "pki", server_names=["srv"], robot_names=["r1", "r2"],
                   viewer_names=["v"], sans=["map.site.example", "10.0.0.7"],
                   endpoint="tls/localhost:7447", map_name="plant", prefix="acme/sogm")
    d = tmp_path / "pki"
    assert pki.directory == d.resolve() and pki.acl_holder == "srv"
    ca = x509.load_pem_x509_certificate((d / "ca.crt").read_bytes())
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    assert stat.S_IMODE(os.stat(d / "ca.key").st_mode) == 0o600
    for name in ("srv", "r1", "r2", "v"):
        cert = x509.load_pem_x509_certificate((d / f"{name}.crt").read_bytes())
        cert.verify_directly_issued_by(ca)  # raises if not signed by the site CA
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == name
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert set(san.get_values_for_type(x509.DNSName)) == {"localhost", "map.site.example"}
        assert {str(ip) for ip in san.get_values_for_type(x509.IPAddress)} == {
            "127.0.0.1", "10.0.0.7"}
        assert not cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
        assert stat.S_IMODE(os.stat(d / f"{name}.key").st_mode) == 0o600
        cfg = config_dict(d / f"{name}.json5")
        tls = cfg["transport"]["link"]["tls"]
        assert tls["enable_mtls"] is True
        assert tls["root_ca_certificate"] == str(d.resolve() / "ca.crt")
        assert tls["connect_certificate"] == str(d.resolve() / f"{name}.crt")
        assert tls["listen_private_key"] == str(d.resolve() / f"{name}.key")
        assert all(Path(v).is_absolute() for k, v in tls.items()
                   if k.endswith(("certificate", "key")))
        assert cfg["scouting"]["multicast"]["enabled"] is False
        zenoh.Config.from_file(str(d / f"{name}.json5"))  # zenoh accepts it as it is
    srv = config_dict(d / "srv.json5")
    assert (srv["mode"], srv["listen"]["endpoints"], srv["connect"]["endpoints"]) == (
        "peer", ["tls/localhost:7447"], [])
    acl = srv["access_control"]
    assert (acl["enabled"], acl["default_permission"]) == (True, "deny")
    keys = {k for r in acl["rules"] for k in r["key_exprs"]}
    assert {"ism/r1/**", "pose/r2", "acme/sogm/plant/submap",
            "acme/sogm/plant/@server/*"} <= keys
    for name in ("r1", "v"):
        cfg = config_dict(d / f"{name}.json5")
        assert (cfg["mode"], cfg["connect"]["endpoints"], cfg["listen"]["endpoints"]) == (
            "client", ["tls/localhost:7447"], [])
        assert "access_control" not in cfg


def test_router_topology_configs(tmp_path: Path) -> None:
    pki = init_pki(tmp_path, server_names=["s1", "s2"], robot_names=["r1"], router_name="rt",
                   endpoint="tls/127.0.0.1:7447")
    rt = config_dict(pki.config("rt"))
    assert (rt["mode"], rt["listen"]["endpoints"]) == ("router", ["tls/127.0.0.1:7447"])
    servers = next(s for s in rt["access_control"]["subjects"] if s["id"] == "servers")
    assert servers["cert_common_names"] == ["s1", "s2", "rt"]
    for name in ("s1", "s2", "r1"):
        cfg = config_dict(pki.config(name))
        assert (cfg["mode"], cfg["connect"]["endpoints"], cfg["listen"]["endpoints"]) == (
            "client", ["tls/127.0.0.1:7447"], [])
        assert "access_control" not in cfg


def test_cli_init_add_renew_and_refusals(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                         ) -> None:
    d = tmp_path / "site"
    assert certs.main(["init", str(d), "--server", "srv", "--robot", "r1", "--viewer", "v",
                       "--endpoint", "tls/127.0.0.1:7447", "--san", "10.1.2.3",
                       "--map", "plant"]) == 0
    assert "srv" in capsys.readouterr().out
    ca_before = (d / "ca.crt").read_bytes()
    r1_before = (d / "r1.crt").read_bytes()
    assert certs.main(["init", str(d), "--server", "srv"]) == 2  # refuses to overwrite
    assert "exists" in capsys.readouterr().err
    assert certs.main(["add", str(d), "--robot", "r2"]) == 0
    assert (d / "ca.crt").read_bytes() == ca_before
    r2 = x509.load_pem_x509_certificate((d / "r2.crt").read_bytes())
    r2.verify_directly_issued_by(x509.load_pem_x509_certificate(ca_before))
    san = r2.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert "10.1.2.3" in {str(ip) for ip in san.get_values_for_type(x509.IPAddress)}
    acl = config_dict(d / "srv.json5")["access_control"]
    r2_rules = {k for r in acl["rules"] if r["id"].startswith("robot-r2-")
                for k in r["key_exprs"]}
    assert r2_rules == {"ism/r2/**", "pose/r2", "sogm/plant/rejections/r2",
                        "sogm/plant/drop/r2/**"}
    assert config_dict(d / "r2.json5")["connect"]["endpoints"] == ["tls/127.0.0.1:7447"]
    assert certs.main(["add", str(d), "--robot", "r2"]) == 2  # duplicate
    assert certs.main(["renew", str(d), "r1", "--days", "30"]) == 0
    assert (d / "r1.crt").read_bytes() != r1_before
    r1 = x509.load_pem_x509_certificate((d / "r1.crt").read_bytes())
    assert dt.timedelta(days=29) < r1.not_valid_after_utc - r1.not_valid_before_utc \
        < dt.timedelta(days=31)
    assert certs.main(["show", str(d)]) == 0
    assert "r2" in capsys.readouterr().out
    assert certs.main(["remove", str(d), "r2"]) == 0
    assert not (d / "r2.key").exists() and not (d / "r2.json5").exists()
    acl = config_dict(d / "srv.json5")["access_control"]
    assert not any("r2" in json.dumps(x) for x in acl["subjects"] + acl["rules"])
    capsys.readouterr()
    assert certs.main(["remove", str(d), "srv"]) == 2  # the only server
    assert "needed" in capsys.readouterr().err
    capsys.readouterr()
    for bad in (["init", str(tmp_path / "a"), "--server", "a/b"],
                ["init", str(tmp_path / "b"), "--server", "s", "--robot", "r*"],
                ["init", str(tmp_path / "c"), "--server", "s", "--robot", "s"],
                ["init", str(tmp_path / "d"), "--server", "s", "--endpoint", "tcp/x:1"],
                ["init", str(tmp_path / "e"), "--server", "s", "--map", "a/b"],
                ["init", str(tmp_path / "f"), "--server", "ca"],
                ["init", str(tmp_path / "g"), "--server", "s", "--san", "a b"],
                ["add", str(tmp_path / "nowhere"), "--robot", "r"]):
        assert certs.main(bad) == 2, bad
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "pki.json").write_text("[1, 2")
    assert certs.main(["add", str(tmp_path / "broken"), "--robot", "r"]) == 2
    err = capsys.readouterr().err
    for code in ("bad_name", "duplicate_name", "bad_endpoint", "bad_map", "bad_san", "no_pki",
                 "bad_manifest"):
        assert code in err
    assert not (tmp_path / "a").exists()


def test_operators_may_drop_any_layers_robots_their_own(tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str],
                                                        ) -> None:
    d = tmp_path / "pki"
    assert certs.main(["init", str(d), "--server", "srv", "--robot", "r1", "--viewer", "v",
                       "--operator", "ops"]) == 0
    assert "operator ops" in capsys.readouterr().out
    assert certs.main(["add", str(d), "--operator", "ops2"]) == 0
    acl = config_dict(d / "srv.json5")["access_control"]
    rules = {r["id"]: r for r in acl["rules"]}
    policies = {p["id"]: p for p in acl["policies"]}
    subjects = {s["id"]: s["cert_common_names"] for s in acl["subjects"]}
    assert subjects["operators"] == ["ops", "ops2"]
    assert rules["operator-drop"]["key_exprs"] == ["sogm/default/drop/**"]
    assert rules["robot-r1-drop"]["key_exprs"] == ["sogm/default/drop/r1/**"]
    assert {"operator-drop", "operator-drop-reply", "drop-decl"} <= \
        set(policies["operators"]["rules"])
    assert not any("drop" in rid for rid in policies["viewers"]["rules"])
    assert config_dict(d / "ops2.json5")["mode"] == "client"
    assert certs.main(["remove", str(d), "ops"]) == 0
    acl = config_dict(d / "srv.json5")["access_control"]
    assert {s["id"]: s["cert_common_names"] for s in acl["subjects"]}["operators"] == ["ops2"]
