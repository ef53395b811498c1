"""``sogm-service bench --zenoh-config / --server-zenoh-config / --secure``: the bench's
Zenoh rows run through a site's configs (mutual TLS and access control), honoured as they are.

Asserts that the rows ran (and through what), never a speed.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration


def _bench(tmp_path: Path, *args: str, timeout: float = 300) -> tuple[int, str, dict]:
    out = tmp_path / "bench.json"
    proc = subprocess.run([sys.executable, "-m", "sogm_service", "bench", *args, "--quick",
                           "--json", str(out)], capture_output=True, text=True,
                          timeout=timeout)
    report = json.loads(out.read_text()) if out.exists() else {}
    return proc.returncode, proc.stdout + proc.stderr, report


def _pki(directory: Path, *robots: str) -> Path:
    cmd = [sys.executable, "-m", "sogm_service", "certs", "init", str(directory),
           "--server", "server"]
    for robot in robots:
        cmd += ["--robot", robot]
    subprocess.run(cmd, check=True, capture_output=True, timeout=60)
    return directory


def test_rows_run_through_the_given_configs_as_the_certificates_robot(tmp_path: Path) -> None:
    """Under the server's access control robot ``alice`` may put only on ``ism/alice/**``:
    the ingestion row fuses every ISM only if the bench publishes as the certificate's name."""
    pki = _pki(tmp_path / "pki", "alice")
    code, out, report = _bench(tmp_path, "submap", "ingest",
                               "--zenoh-config", str(pki / "alice.json5"),
                               "--server-zenoh-config", str(pki / "server.json5"))
    assert code == 0, out
    assert report["transport_protocol"] == "tls"
    assert "publishing as 'alice'" in report["transport"]
    rows = {r["name"]: r for r in report["rows"]}
    assert not rows["submap_zenoh_256x4"]["note"].startswith("error"), rows
    assert rows["ingest_zenoh_256"]["details"]["not_fused"] == 0.0, rows


def test_a_client_config_from_another_ca_cannot_reach_the_bench_servers(tmp_path: Path) -> None:
    ours = _pki(tmp_path / "ours", "alice")
    theirs = _pki(tmp_path / "theirs", "alice")
    code, out, report = _bench(tmp_path, "submap",
                               "--zenoh-config", str(theirs / "alice.json5"),
                               "--server-zenoh-config", str(ours / "server.json5"))
    assert code == 1, out
    (row,) = report["rows"]
    assert row["note"].startswith("error"), row


def test_secure_makes_its_own_pki(tmp_path: Path) -> None:
    code, out, report = _bench(tmp_path, "submap", "--secure")
    assert code == 0, out
    assert report["transport_protocol"] == "tls" and "sogm-bench-pki-" in report["zenoh_config"]
    assert not Path(report["zenoh_config"]).exists()  # the dev PKI is gone with the run


def test_bad_flags_are_refused_in_one_line(tmp_path: Path) -> None:
    code, out, _ = _bench(tmp_path, "submap", "--zenoh-config", str(tmp_path / "nope.json5"))
    assert code == 2 and "--zenoh-config" in out and "no such file" in out
    code, out, _ = _bench(tmp_path, "submap", "--secure", "--zenoh-config",
                          str(tmp_path / "x.json5"))
    assert code == 2 and "not both" in out


def test_the_cluster_rows_run_under_the_access_control(tmp_path: Path) -> None:
    """A robot may ask one cluster member by its key (``member/<id>/submap``): the row that
    compares a non-owner with the owner runs through the dev PKI's access control."""
    code, out, report = _bench(tmp_path, "cluster_submap", "--secure")
    assert code == 0, out
    (row,) = report["rows"]
    assert row["details"]["tiles_served"] > 0, row
