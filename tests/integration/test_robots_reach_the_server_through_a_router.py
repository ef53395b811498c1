"""Robots + router + server: three processes, robots and viewers reach the server via the router."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zenoh

from sogm_service.client.mapclient import MapClient
from sogm_service.client.session import free_tcp_endpoint
from tests.conftest import start_server, wait_processed, wait_until

pytestmark = pytest.mark.integration


def test_robot_reaches_server_through_python_router(tmp_path: Path) -> None:
    router_ep = free_tcp_endpoint()
    router = subprocess.Popen([sys.executable, "-m", "sogm_service", "router", "--listen",
                               router_ep], stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT,
                              env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        srv = start_server(tmp_path, {"zenoh": {"mode": "peer", "listen": [free_tcp_endpoint()],
                                                "connect": [router_ep]}})
        try:
            with MapClient.connect(router_ep, timeout=2.0) as robot:
                assert wait_until(lambda: bool(robot.servers(timeout=1.0)), 15)
                robot.publish_ism("ism/robot7/laser/obstacle",
                                  np.full((20, 20), 240, np.uint8), resolution=0.05)
                wait_processed(robot, 1)
                sub = robot.submap(x=0.5, y=0.5, width=1.0, height=1.0)
            assert sub.layers == ["robot7/laser/obstacle"]
            assert sub.probabilities().min() > 0.9
        finally:
            assert srv.terminate() == 0
    finally:
        router.send_signal(signal.SIGTERM)
        assert router.wait(15) == 0


def test_behind_a_router_a_get_is_computed_by_one_server_only(tmp_path: Path) -> None:
    """The map's queryables are complete (each server answers for the whole map): through a
    router a client's get reaches one server, not every server of the map."""
    router_ep = free_tcp_endpoint()
    router = subprocess.Popen([sys.executable, "-m", "sogm_service", "router", "--listen",
                               router_ep], stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT,
                              env={**os.environ, "PYTHONUNBUFFERED": "1"})
    servers = []
    try:
        for name in ("s1", "s2"):
            servers.append(start_server(tmp_path, {"zenoh": {
                "mode": "peer", "listen": [free_tcp_endpoint()], "connect": [router_ep]}},
                name=name))
        with MapClient.connect(router_ep, timeout=2.0) as robot:
            def asked() -> list[int]:
                out = []
                for reply in robot.session.get(robot.key("stats"),
                                               target=zenoh.QueryTarget.ALL,
                                               consolidation=zenoh.ConsolidationMode.NONE,
                                               timeout=5.0):
                    if reply.ok is not None:
                        got = msgpack.unpackb(reply.ok.payload.to_bytes())
                        out.append(got["counters"].get("queries_info", 0))
                return out

            assert wait_until(lambda: len(asked()) == 2, 15)
            for _ in range(6):
                robot.info()
            assert sum(asked()) == 6  # incomplete queryables: 12, both servers computing each
    finally:
        for srv in servers:
            assert srv.terminate() == 0
        router.send_signal(signal.SIGTERM)
        assert router.wait(15) == 0
