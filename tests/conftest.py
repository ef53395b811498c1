"""Shared fixtures: real server processes and client sessions on 127.0.0.1 (multicast off)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from sogm_service.client.mapclient import MapClient
from sogm_service.client.session import free_tcp_endpoint, wait_listening


@dataclass
class ServerProcess:
    """A ``sogm-service serve`` child process that this test started (and alone may end)."""

    proc: subprocess.Popen[bytes]
    endpoint: str
    config_path: Path
    log_path: Path

    def client(self, timeout: float = 5.0) -> MapClient:
        return MapClient.connect(self.endpoint, timeout=timeout)

    def terminate(self, timeout: float = 15.0) -> int:
        """SIGTERM and wait; returns the exit code (kills by pid only if it hangs)."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)
            raise

    def log(self) -> str:
        return self.log_path.read_text(encoding="utf-8", errors="replace")

    @property
    def server_id(self) -> str:
        """Its Zenoh id, from serve's start line (``serving map 'm' as <id> on ...``)."""
        for line in self.log().splitlines():
            if "serving map" in line and " as " in line:
                return line.split(" as ", 1)[1].split()[0].rstrip(";")
        raise RuntimeError(f"no start line in {self.log_path}")


def toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{toml_value(str(k))} = {toml_value(x)}"
                                for k, x in v.items()) + " }"
    return '"' + str(v).replace("\\", "\\\\").replace('"', '\\"') + '"'


def write_config(path: Path, sections: dict[str, dict[str, Any]],
                 ism: list[dict[str, Any]] | None = None) -> Path:
    lines = []
    for name, fields in sections.items():
        lines.append(f"[{name}]")
        lines += [f"{k} = {toml_value(v)}" for k, v in fields.items()]
    for source in ism or []:
        lines.append("[[ism]]")
        for k, v in source.items():
            if isinstance(v, dict):
                continue
            lines.append(f"{k} = {toml_value(v)}")
        for k, v in source.items():
            if isinstance(v, dict):
                lines.append(f"[ism.{k}]")
                lines += [f"{kk} = {toml_value(vv)}" for kk, vv in v.items()]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def start_server(tmp_path: Path, sections: dict[str, dict[str, Any]] | None = None,
                 ism: list[dict[str, Any]] | None = None, name: str = "server",
                 endpoint: str | None = None, wait: float = 20.0,
                 servers: int = 1) -> ServerProcess:
    """Start ``python -m sogm_service serve`` with a config; return once it is discoverable
    (``servers``: how many live servers of the map its endpoint must show, itself included,
    when it is connected to others)."""
    sections = {k: dict(v) for k, v in (sections or {}).items()}
    listen = sections.setdefault("zenoh", {}).get("listen")
    endpoint = listen[0] if listen else (endpoint or free_tcp_endpoint())
    sections["zenoh"]["listen"] = [endpoint]
    config_path = write_config(tmp_path / f"{name}.toml", sections, ism)
    log_path = tmp_path / f"{name}.log"
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "sogm_service", "serve", "--config", str(config_path)],
            stdout=log, stderr=subprocess.STDOUT, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    server = ServerProcess(proc, endpoint, config_path, log_path)
    try:
        _wait_until_discoverable(server, sections.get("map", {}).get("name", "default"),
                                 time.monotonic() + wait, servers)
    except BaseException:
        if proc.poll() is None:  # never leave a child behind, whatever went wrong
            proc.kill()
            proc.wait(5)
        raise
    return server


def _wait_until_discoverable(server: ServerProcess, map_name: str, deadline: float,
                             servers: int) -> None:
    wait_listening(server.endpoint, deadline - time.monotonic(),
                   lambda: server.proc.poll() is not None, server.log, poll_s=0.05)
    with MapClient.connect(server.endpoint, map_name=map_name, timeout=1.0) as probe:
        while time.monotonic() < deadline:
            if server.proc.poll() is not None:
                raise RuntimeError(
                    f"server exited with {server.proc.returncode}:\n{server.log()}")
            try:
                if len(probe.servers(timeout=1.0)) >= servers:
                    return
            except Exception:
                pass
            time.sleep(0.1)
    raise RuntimeError(f"server did not come up:\n{server.log()}")


@pytest.fixture
def server(tmp_path: Path) -> Iterator[ServerProcess]:
    srv = start_server(tmp_path)
    yield srv
    if srv.proc.poll() is None:
        srv.terminate()


def wait_until(predicate: Any, timeout: float = 10.0, interval: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(interval)
    return bool(predicate())


def wait_processed(client: MapClient, n: int, timeout: float = 15.0) -> dict[str, int]:
    """Wait until the server has fused or rejected ``n`` ISMs; returns its counters."""
    counters: dict[str, int] = {}

    def done() -> bool:
        nonlocal counters
        counters = client.stats().counters
        return counters.get("isms_fused", 0) + counters.get("isms_rejected", 0) >= n

    wait_until(done, timeout)
    return counters


@pytest.fixture
def procs() -> Iterator[list[ServerProcess]]:
    """Server processes a test starts; any still running at its end is killed (ours, by pid)."""
    started: list[ServerProcess] = []
    yield started
    for p in started:
        if p.proc.poll() is None:
            p.proc.kill()
            p.proc.wait(10)


def spy_mosaics(tiled: Any) -> list[tuple[int, ...]]:
    """The shapes of the mosaics ``tiled`` builds from now on (a list that fills as it reads):
    which windows take the full path (a box at map resolution) and which are gathered."""
    built: list[tuple[int, ...]] = []
    original = tiled.mosaic

    def spy(box: tuple[int, int, int, int], ids: list[int], now: float | None = None) -> Any:
        out = original(box, ids, now)
        built.append(out.shape)
        return out

    tiled.mosaic = spy
    return built


@pytest.fixture(scope="session")
def seaweedfs(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    """One real S3 server (SeaweedFS from the test extra's wheel) for the whole session, on
    127.0.0.1, its data in a temporary directory, ended by its pid (``tests/s3server.py``)."""
    from tests.s3server import start_seaweedfs

    server = start_seaweedfs(tmp_path_factory.mktemp("seaweedfs"))
    yield server
    server.stop()


@pytest.fixture
def router() -> Iterator[str]:
    """A ``sogm-service router`` on a free port on 127.0.0.1 (its endpoint), ended by its pid."""
    endpoint = free_tcp_endpoint()
    proc = subprocess.Popen([sys.executable, "-m", "sogm_service", "router", "--listen",
                             endpoint], stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    yield endpoint
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
