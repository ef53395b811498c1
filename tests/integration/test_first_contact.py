"""First contact and everyday use: publishers hear back, errors are one line with
exit 2, the first supercells query succeeds on a fresh numba cache, the CLI's options work.

Real server processes and Zenoh sessions on 127.0.0.1 throughout (tests/conftest.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from sogm_service.client import (
    ConnectError,
    IsmNotFusedError,
    MapClient,
    Pose2D,
    ServiceError,
)
from sogm_service.client.session import free_tcp_endpoint
from sogm_service.service.config import load_config
from sogm_service.wire.messages import RejectionReport
from tests.conftest import ServerProcess, start_server, wait_until, write_config

pytestmark = pytest.mark.integration

CLI = [sys.executable, "-m", "sogm_service"]


def run_cli(*args: str, timeout: float = 60.0, env: dict[str, str] | None = None,
            cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, **(env or {})}, cwd=cwd)


def one_line_error(proc: subprocess.CompletedProcess[str]) -> str:
    """The refusal: exit 2, exactly one line on stderr, no traceback."""
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    return lines[0]


# --------------------------------------------------------------------- publishers hear back
def test_publish_wait_then_query_always_sees_the_ism(server: ServerProcess) -> None:
    """With wait=True the ISM is in the map when publish_ism returns: 20 tries, 20 hits."""
    with server.client() as client:
        for k in range(20):
            x0 = 3.0 * k
            client.publish_ism(f"ism/r{k % 3}/laser/obstacle", np.full((20, 20), 240, np.uint8),
                               resolution=0.05, origin=Pose2D(x0, 0.0, 0.0), wait=True)
            sub = client.submap(x=x0 + 0.5, y=0.5, width=0.8, height=0.8, resolution=0.05,
                                layers=[f"r{k % 3}/laser/obstacle"])
            p = sub.probabilities()
            assert (p > 0.9).all(), f"try {k}: the fused ISM is not in the map yet"


def test_rejections_come_back_to_the_publisher(server: ServerProcess) -> None:
    reports: list[tuple[str, RejectionReport]] = []
    got = threading.Event()
    with server.client() as client:
        sub = client.subscribe_rejections(lambda r, rep: (reports.append((r, rep)), got.set()))
        time.sleep(0.3)  # the subscription reaches the server
        with pytest.raises(IsmNotFusedError) as err:
            client.publish_ism("ism/robot7/laser/obstacle", np.zeros((4, 4), np.uint8),
                               resolution=0.05, frame="odom", wait=True)
        assert err.value.code == "wrong_frame"
        assert "odom" in err.value.message
        assert got.wait(5)
        robot, report = reports[0]
        assert robot == "robot7"
        assert (report.code, report.key) == ("wrong_frame", "ism/robot7/laser/obstacle")
        assert report.id is not None and len(report.message) <= 200
        sub.undeclare()
        # Too large for the map: the tile bound, reported with its reason.
        with pytest.raises(IsmNotFusedError) as err:
            client.publish_ism("ism/robot7/laser/obstacle", np.zeros((4, 4), np.uint8),
                               resolution=500.0, wait=True)
        assert err.value.code == "too_large"
        # A payload that is not msgpack at all, published by hand with an id: rejected, acked.
        client.session.put("ism/robot7/raw", b"\xc1garbage", attachment=b"raw-1")
        deadline = time.monotonic() + 10
        while (ack := client.ack("raw-1")).status != "rejected":
            assert time.monotonic() < deadline, ack
            time.sleep(0.05)
        assert ack.code == "malformed_msgpack"


def test_wait_fused_waits_for_every_ism_under_load(server: ServerProcess) -> None:
    """200 ISMs published back to back, then one wait: each one fused, in the map."""
    with server.client() as client:
        grid = np.full((64, 64), 200, np.uint8)
        for k in range(200):
            client.publish_ism("ism/fleet/laser/obstacle", grid, resolution=0.05,
                               origin=Pose2D(0.1 * (k % 10), 0.0, 0.0))
        acks = client.wait_fused(timeout=60)
        assert len(acks) == 200 and {a.status for a in acks} == {"fused"}
        assert client.wait_fused() == []  # nothing left to wait for
        assert client.stats().counters["isms_fused"] >= 200
        unknown = client.ack("never-published-0")
        assert unknown.status == "unknown"
        with pytest.raises(ServiceError) as err:
            client.ack("bad id with spaces")
        assert (err.value.code, err.value.parameter) == ("bad_parameter", "id")


def test_connect_to_nothing_raises_connect_error() -> None:
    endpoint = free_tcp_endpoint()
    with pytest.raises(ConnectError, match=f"no sogm-service reachable at {endpoint}"):
        MapClient.connect(endpoint)
    with pytest.raises(ConnectError, match="names no protocol"):
        MapClient.connect("127.0.0.1:7447")


# --------------------------------------------------------------------------- the CLI
def test_cli_publish_waits_and_reports_the_server_reason(server: ServerProcess,
                                                         tmp_path: Path) -> None:
    grid = tmp_path / "scan.npy"
    np.save(grid, np.full((30, 40), 230, np.uint8))
    ok = run_cli("publish-ism", str(grid), "--connect", server.endpoint, "--key",
                 "ism/r1/laser/obstacle", "--resolution", "0.05", "--x", "1", "--yaw-deg", "90")
    assert ok.returncode == 0, ok.stderr
    assert ok.stdout.startswith("fused 40x30 prob_u8 ISM on ism/r1/laser/obstacle")
    q = run_cli("query", "submap", "--connect", server.endpoint, "--x", "0.25", "--y", "1",
                "--width", "1", "--height", "1", "--json")
    assert q.returncode == 0, q.stderr
    reply = json.loads(q.stdout)
    assert reply["kind"] == "submap" and reply["occupied_fraction"] > 0.5  # rotated 90 deg
    bad = run_cli("publish-ism", str(grid), "--connect", server.endpoint, "--key",
                  "ism/r1/laser/obstacle", "--resolution", "0.05", "--frame", "odom")
    line = one_line_error(bad)
    assert "[wrong_frame]" in line and "odom" in line


def test_cli_mistakes_are_one_line_with_exit_2(tmp_path: Path) -> None:
    endpoint = free_tcp_endpoint()
    grid = tmp_path / "g.npy"
    np.save(grid, np.zeros((10, 3, 1), np.uint8))
    cases = {
        "no server": (["query", "info", "--connect", endpoint],
                      f"no sogm-service reachable at {endpoint}: is 'sogm-service serve' "
                      "running?"),
        "no protocol": (["query", "info", "--connect", "127.0.0.1:7447"], "names no protocol"),
        "bad shape": (["publish-ism", str(grid), "--resolution", "0.1", "--connect", endpoint],
                      "2-D grid"),
        "missing file": (["publish-ism", str(tmp_path / "nope.npy"), "--resolution", "0.1"],
                         "no such file"),
        "yaw in degrees": (["query", "submap", "--yaw", "90", "--connect", endpoint],
                           "--yaw-deg 90"),
    }
    for name, (argv, expected) in cases.items():
        line = one_line_error(run_cli(*argv))
        assert expected in line, (name, line)


def test_serve_mistakes_are_one_line_with_exit_2(tmp_path: Path) -> None:
    bad_endpoint = write_config(tmp_path / "bad.toml", {"zenoh": {"listen": ["localhost"]}})
    assert "names no protocol" in one_line_error(run_cli("serve", "--config",
                                                         str(bad_endpoint)))
    typed = write_config(tmp_path / "typed.toml", {"map": {"resolution": "0.1"}})
    assert "map.resolution" in one_line_error(run_cli("serve", "--config", str(typed)))
    # A store in use by a running server.
    store = tmp_path / "store"
    srv = start_server(tmp_path, {"storage": {"directory": str(store)}})
    try:
        line = one_line_error(run_cli("serve", "--listen", free_tcp_endpoint(),
                                      "--storage", str(store)))
        assert "store" in line.lower()
    finally:
        srv.terminate()


def test_cli_version_help_and_log_options() -> None:
    version = run_cli("--version")
    assert version.returncode == 0 and version.stdout.startswith("sogm-service ")
    helptext = run_cli("query", "submap", "-h").stdout
    for option in ("--yaw-deg", "--encoding", "--json", "--log-level", "(m)", "default:"):
        assert option in helptext, option
    assert run_cli("schemas", "--check", "-q", "--out",
                   str(Path(__file__).resolve().parents[2] / "schemas")).returncode == 0
    # -v before or after a delegated subcommand: it still runs (its own help here).
    for argv in (["-v", "tiles", "--help"], ["tiles", "-v", "--help"],
                 ["tiles", "--log-level", "warning", "--help"]):
        proc = run_cli(*argv)
        assert proc.returncode == 0 and "usage" in proc.stdout.lower(), (argv, proc.stderr)


def test_serve_honours_the_configs_log_level(tmp_path: Path) -> None:
    from sogm_service.client.session import wait_listening

    endpoint = free_tcp_endpoint()
    config = tmp_path / "quiet.toml"
    config.write_text(f'log_level = "warning"\n[zenoh]\nlisten = ["{endpoint}"]\n')
    log = tmp_path / "quiet.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen([*CLI, "serve", "--config", str(config)], stdout=out,
                                stderr=subprocess.STDOUT)
    try:
        wait_listening(endpoint, 30, lambda: proc.poll() is not None,
                       lambda: log.read_text(errors="replace"))
        with MapClient.connect(endpoint) as client, pytest.raises(IsmNotFusedError):
            # Listening is not ready: the ISM subscriber and the ack queryable are declared
            # later; the server's liveliness token says they are (a busy CI lost the ISM).
            assert wait_until(lambda: bool(client.servers(timeout=1.0)), 30)
            client.publish_ism("ism/r/x", np.zeros((2, 2), np.uint8), resolution=0.1,
                               frame="odom", wait=True)
    finally:
        proc.terminate()
        proc.wait(15)
    text = log.read_text(errors="replace")
    assert "WARNING" in text and "wrong_frame" in text  # the warning is logged...
    assert " INFO " not in text  # ... the info lines are not


def test_a_stopped_server_leaves_no_warm_up_child(tmp_path: Path) -> None:
    import signal

    from sogm_service.service.server.server import MapServer

    config = load_config(write_config(tmp_path / "s.toml",
                                      {"zenoh": {"listen": [free_tcp_endpoint()]}}))
    server = MapServer(config).start()
    try:
        assert wait_until(lambda: server._warm_up_child is not None, 10)
    finally:
        server.stop()
    child = server._warm_up_child
    assert child is not None and child.poll() == -signal.SIGTERM  # ended, not left to run


# ------------------------------------------------------------- the Quick start cannot fail


def test_read_only_install_imports_and_runs_the_kernels(tmp_path: Path) -> None:
    """In a process whose package directory cannot be written and whose home is unusable,
    the kernels still load (numba's cache decorator finds no locator there: the cache falls
    back to a writable directory)."""
    code = ("import sogm_service.core.sevds.numba_cache as m, pathlib, os;"
            "m._HERE = pathlib.Path('/proc/self');"
            "from sogm_service.core.sevds.segment import warm_up; warm_up();"
            "print(os.environ['NUMBA_CACHE_DIR'])")
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env.update(HOME="/proc/self/nohome", XDG_CACHE_HOME=str(tmp_path / "xdg"))
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == str(tmp_path / "xdg" / "sogm-service" / "numba")
    assert any((tmp_path / "xdg").rglob("*.nbi"))


def test_first_supercells_query_on_a_fresh_cache_with_both_cores_busy(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The Quick start's failure: numba compiles SEVDS on a busy machine while the client's
    5 s ran out.  Now: a fresh numba cache, two CPU burners we own, the CLI's supercells query
    right after start-up -- it succeeds (the server warms up in the background and the client
    waits within its supercells budget, retrying on ``warming_up``)."""
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "numba-cache"))
    burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    try:
        srv = start_server(tmp_path, wait=60)
        try:
            with srv.client() as client:
                client.publish_ism("ism/r1/laser/obstacle", np.full((64, 64), 230, np.uint8),
                                   resolution=0.05, wait=True, timeout=60)
            png = tmp_path / "graph.png"
            proc = run_cli("query", "supercells", "--connect", srv.endpoint, "--x", "1.6",
                           "--y", "1.6", "--width", "3.2", "--height", "3.2", "--png", str(png),
                           timeout=180)
            assert proc.returncode == 0, proc.stderr
            assert proc.stdout.startswith("supercells: ") and png.stat().st_size > 10_000
        finally:
            srv.terminate()
        assert any((tmp_path / "numba-cache").rglob("*.nbi"))  # the cache went where told
    finally:
        for b in burners:
            b.kill()
            b.wait(5)


def test_serve_with_bad_config_exits_2_with_the_reason(tmp_path: Path) -> None:
    path = tmp_path / "bad.toml"
    path.write_text("[map]\neps0 = 0.7\n")
    proc = subprocess.run([sys.executable, "-m", "sogm_service", "serve", "--config",
                           str(path)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert "map.eps0" in proc.stderr
