"""Robots + router + server: three processes, robots and viewers reach the server via the router."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sogm_service.service.client import MapClient
from sogm_service.service.session import free_tcp_endpoint
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
