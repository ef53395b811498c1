"""Who may take evidence back on a secure site: the real ``serve`` over mutual TLS with the
access control ``sogm-service certs init`` writes (by certificate common name, default deny).

The drop key carries the layer pattern (``sogm/default/drop/<pattern>``), and Zenoh's access
control allows a query only when one of a rule's key expressions *includes* the query's key
expression: a robot allowed ``drop/<robot>/**`` reaches the server with its own patterns only,
never with a wildcard or a character set in the robot's chunk (``*``, ``robot$*``,
``robot[12]``), which would match other robots' layers.  Denied queries never reach the server
(its ``queries_drop`` counter stays 0) and leave the map bit for bit; an operator drops any.
Both topologies: the server listening and carrying the rules, and a router carrying them with
the server one of its clients.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from sogm_service.apps.certs import Pki, init_pki
from sogm_service.client.mapclient import MapClient
from sogm_service.client.session import free_tcp_endpoint, wait_listening
from sogm_service.core.geometry import Pose2D
from sogm_service.wire.errors import QueryTimeoutError

pytestmark = pytest.mark.integration

DENIED_WAIT = 1.5  # seconds a denied drop waits for a reply that never comes
WINDOW: dict[str, Any] = dict(x=6.0, y=4.0, width=12.0, height=8.0, resolution=0.5,
                              interp="nearest", encoding="logodds_i16")


@dataclass
class SecureServer:
    pki: Pki
    proc: subprocess.Popen[bytes]
    log: Path
    procs: list[subprocess.Popen[bytes]]

    def client(self, name: str, timeout: float = 10.0) -> MapClient:
        session = zenoh.open(zenoh.Config.from_file(str(self.pki.config(name))))
        return MapClient(session, timeout=timeout, owns_session=True)


def child(args: list[str], log: Path) -> subprocess.Popen[bytes]:
    with open(log, "wb") as out:
        return subprocess.Popen([sys.executable, "-m", "sogm_service", *args], stdout=out,
                                stderr=subprocess.STDOUT,
                                env={**os.environ, "PYTHONUNBUFFERED": "1"})


@pytest.fixture(scope="module", params=["direct", "router"])
def secure(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory,
           ) -> Iterator[SecureServer]:
    d = tmp_path_factory.mktemp(f"secure-drop-{request.param}")
    router = "rt" if request.param == "router" else None
    pki = init_pki(d / "pki", server_names=["srv"], robot_names=["robot1", "robot2"],
                   viewer_names=["view"], operator_names=["ops"], router_name=router,
                   endpoint=free_tcp_endpoint().replace("tcp/", "tls/", 1))
    toml = d / "serve.toml"
    toml.write_text(f'[zenoh]\nconfig_file = "{pki.config("srv")}"\n'
                    f'[map]\nresolution = 0.5\ntile_size = 16\n'
                    f'[storage]\ndirectory = "{d / "tiles"}"\n', encoding="utf-8")
    log = d / "serve.log"
    procs: list[subprocess.Popen[bytes]] = []
    try:
        if router:
            procs.append(child(["router", "--zenoh-config", str(pki.config(router))],
                               d / "router.log"))
        proc = child(["serve", "--config", str(toml)], log)
        procs.append(proc)
        wait_listening(pki.endpoint.replace("tls/", "tcp/", 1), 60,
                       lambda: any(p.poll() is not None for p in procs),
                       lambda: log.read_text(errors="replace"))
        server = SecureServer(pki, proc, log, procs)
        with server.client("robot1", timeout=1.0) as probe:
            assert eventually(lambda: len(probe.servers()) == 1), log.read_text()
        yield server
    finally:
        for p in reversed(procs):  # the server first, then its router
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
                try:
                    p.wait(15)
                except subprocess.TimeoutExpired:
                    p.kill()  # our own child, by its pid
                    p.wait(5)


def eventually(pred: Any, tries: int = 200) -> bool:
    ev = threading.Event()
    for _ in range(tries):
        if pred():
            return True
        ev.wait(0.05)
    return bool(pred())


def publish(client: MapClient, robot: str, layer: str, x: float) -> None:
    grid = np.random.default_rng(len(layer) + int(x)).integers(0, 101, (16, 16)).astype(np.int8)
    client.publish_ism(f"ism/{robot}/{layer}", grid, resolution=0.5, origin=Pose2D(x, 0.0, 0.0))


def test_a_robot_drops_only_its_own_layers_an_operator_any(secure: SecureServer) -> None:
    with secure.client("robot1") as robot1, secure.client("robot2") as robot2, \
            secure.client("ops") as ops:
        publish(robot1, "robot1", "laser/obstacle", 0.0)
        publish(robot1, "robot1", "camera/person", 2.0)
        publish(robot2, "robot2", "laser/obstacle", 4.0)
        assert eventually(lambda: robot1.stats().counters.get("isms_fused", 0) == 3)
        layers = ["robot1/camera/person", "robot1/laser/obstacle", "robot2/laser/obstacle"]
        assert sorted(robot1.info().layers) == layers
        before = np.asarray(robot1.submap(layers=layers, **WINDOW).data)

        robot1.timeout = DENIED_WAIT
        for pattern in ("robot2/*", "*", "*/laser/obstacle", "robot*/laser/obstacle",
                        "robot[12]/laser/obstacle", "robot2/laser/obstacle"):
            with pytest.raises(QueryTimeoutError):
                robot1.drop_layers(pattern)
        with secure.client("view", timeout=DENIED_WAIT) as viewer, \
                pytest.raises(QueryTimeoutError):
            viewer.drop_layers("robot2/*")
        counters = ops.stats().counters
        assert counters.get("queries_drop", 0) == 0  # not one reached the server
        assert sorted(ops.info().layers) == layers
        assert np.array_equal(np.asarray(ops.submap(layers=layers, **WINDOW).data), before)

        # The command says why nothing answered: a server is alive, the drop was denied.
        cli = subprocess.run(
            [sys.executable, "-m", "sogm_service", "layers", "drop", "robot2/*", "--timeout",
             str(DENIED_WAIT), "--zenoh-config", str(secure.pki.config("robot1"))],
            capture_output=True, text=True, timeout=60, check=False)
        assert cli.returncode == 2 and "may not drop these layers" in cli.stderr, cli.stderr
        assert sorted(ops.info().layers) == layers

        robot1.timeout = 10.0
        own = robot1.drop_layers("robot1/camera/*")
        assert own.layers == ["robot1/camera/person"] and own.stored
        dropped = ops.drop_layers("robot2/*")
        assert dropped.layers == ["robot2/laser/obstacle"] and dropped.stored
        assert ops.info().layers == ["robot1/laser/obstacle"]
        after = np.asarray(ops.submap(layers=["robot1/laser/obstacle"], **WINDOW).data)
        assert np.array_equal(after[0], before[1])  # robot1's obstacles bit for bit
        assert ops.stats().counters.get("queries_drop") == 2
