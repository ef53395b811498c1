"""A drop-out between robot and server: the router between them stopped (SIGTERM by pid) and
started again on the same port.  The client's session reconnects by itself, a query asked
during the gap answers once the router is back within its budget, and ISMs offered during the
gap follow the offline policy: the latest per key arrives after, the rest are counted.  ISMs
put on a route no server heard (a subscriber that is not a server) are found by the server's
acknowledgements and the newest is sent again."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sogm_service.client.mapclient import MapClient
from sogm_service.client.offline import has_route
from sogm_service.client.session import free_tcp_endpoint
from sogm_service.core.geometry import Pose2D
from sogm_service.sim.fleet import run_fleet
from sogm_service.sim.worlds import World
from tests.conftest import ServerProcess, start_server, wait_processed, wait_until
from tests.unit.sim import test_sensors as sim

pytestmark = pytest.mark.integration

warehouse = sim.warehouse  # the simulator tests' world fixture

GAP_S = 2.0


def start_router(endpoint: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen([sys.executable, "-m", "sogm_service", "router", "--listen",
                             endpoint], stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})


def stop(router: subprocess.Popen[bytes]) -> None:
    if router.poll() is None:
        router.send_signal(signal.SIGTERM)
    assert router.wait(15) == 0


@pytest.fixture
def behind_a_router(tmp_path: Path) -> Any:
    """A router and a server (a peer connected to it); yields (router endpoint, server,
    a box holding the router process, so a test may replace it)."""
    router_ep = free_tcp_endpoint()
    box = {"router": start_router(router_ep)}
    srv: ServerProcess | None = None
    try:
        srv = start_server(tmp_path, {"zenoh": {"mode": "peer", "listen": [free_tcp_endpoint()],
                                                "connect": [router_ep]}})
        yield router_ep, srv, box
    finally:
        if srv is not None:
            assert srv.terminate() == 0
        stop(box["router"])


def test_a_client_rides_out_a_router_restart(behind_a_router: Any) -> None:
    router_ep, srv, box = behind_a_router
    key = "ism/robot1/laser/obstacle"
    with MapClient.connect(router_ep, timeout=2.0) as robot, srv.client() as direct:
        assert wait_until(lambda: bool(robot.servers(timeout=1.0)), 15)
        robot.publish_ism(key, np.full((20, 20), 240, np.uint8), resolution=0.05,
                          origin=Pose2D(0.0, 0.0), wait=True)
        pub = robot._publishers[key]
        poses: list[str] = []  # a subscriber declared before the drop-out
        robot.subscribe_poses(lambda name, _msg: poses.append(name), "pose/viewer1")
        stop(box["router"])
        assert wait_until(lambda: not has_route(pub), 5)
        # During the gap: five ISMs on two keys, each at its own place.
        for n in range(4):
            robot.publish_ism(key, np.full((20, 20), 240, np.uint8), resolution=0.05,
                              origin=Pose2D(2.0 * (n + 1), 0.0))
        robot.publish_ism("ism/robot1/camera/floor", np.full((20, 20), 20, np.uint8),
                          resolution=0.05, origin=Pose2D(0.0, 4.0))
        held = robot.offline_stats()
        assert (held.held, held.dropped_superseded, held.outages) == (2, 3, 1)
        answer: dict[str, Any] = {}

        def ask() -> None:  # a query asked during the gap, with a budget that outlasts it
            started = time.monotonic()
            try:
                answer["stats"] = robot.stats()
            except Exception as exc:  # reported below: the test says which
                answer["error"] = exc
            answer["s"] = time.monotonic() - started

        asker = threading.Thread(target=ask)
        robot.timeout = GAP_S + 6.0
        asker.start()
        time.sleep(GAP_S)
        box["router"] = start_router(router_ep)
        asker.join(15)
        robot.timeout = 2.0
        assert "error" not in answer, answer
        assert answer["s"] > GAP_S - 0.5  # it was asked while nothing could answer
        # The session reconnected: the held ISMs go out, the publisher and subscribers work.
        assert robot.flush_offline(timeout=10.0) == 0
        stats = robot.offline_stats()
        assert (stats.offered, stats.sent, stats.flushed, stats.dropped) == (6, 3, 2, 3)
        counters = wait_processed(direct, 3)
        assert counters.get("isms_fused", 0) == stats.offered - stats.dropped == 3
        latest = direct.submap(x=8.5, y=0.5, width=1.0, height=1.0,
                               layers=["robot1/laser/obstacle"])
        superseded = direct.submap(x=4.5, y=0.5, width=1.0, height=1.0,
                                   layers=["robot1/laser/obstacle"])
        assert latest.probabilities().min() > 0.9  # the kept latest arrived
        assert np.all(superseded.probabilities() == 0.5)  # a dropped one never did
        robot.publish_ism(key, np.full((20, 20), 240, np.uint8), resolution=0.05, wait=True)
        with MapClient.connect(router_ep, timeout=2.0) as other:  # the subscriber is back
            assert wait_until(lambda: other.publish_pose("viewer1", 1.0, 1.0) is None
                              and bool(poses), 10)


def test_a_fleet_publishing_through_a_drop_out(behind_a_router: Any, warehouse: World) -> None:
    router_ep, srv, box = behind_a_router
    result: dict[str, Any] = {}

    def fleet() -> None:
        try:
            result["stats"] = run_fleet(warehouse, router_ep, robots=2, duration_s=8.0,
                                        rate_hz=4.0, seed=1, realtime=True, speed=1.0,
                                        flush_s=10.0)
        except Exception as exc:
            result["error"] = exc

    thread = threading.Thread(target=fleet)
    thread.start()
    time.sleep(2.5)
    stop(box["router"])
    time.sleep(GAP_S)
    box["router"] = start_router(router_ep)
    thread.join(40)
    assert not thread.is_alive()
    assert "error" not in result, result  # no exception escapes the fleet
    stats = result["stats"]
    assert stats.isms_dropped > 0 and stats.isms_flushed > 0 and stats.outages > 0, stats
    with srv.client() as direct:
        counters = wait_processed(direct, stats.isms_sent - stats.isms_lost)
    # Every ISM is accounted for: fused, dropped by the policy, or (the few on their way as the
    # router went) unknown to the server by its acknowledgements.
    assert stats.isms_lost == 0, stats  # a stopped router is noticed at once: nothing lost
    fused = counters.get("isms_fused", 0)
    assert fused + stats.isms_dropped + stats.isms_lost == stats.isms, (counters, stats)


def test_isms_no_server_received_are_sent_again(tmp_path: Path) -> None:
    router_ep = free_tcp_endpoint()
    router = start_router(router_ep)
    srv: ServerProcess | None = None
    key = "ism/robot1/laser/obstacle"
    try:
        assert wait_until(lambda: _listening(router_ep), 15)
        with MapClient.connect(router_ep, timeout=2.0) as robot, \
                MapClient.connect(router_ep) as decoy:
            # A route for the robot's key, but no server behind it: the puts reach no map.
            decoy.session.declare_subscriber("ism/**", lambda _sample: None)
            for n in range(3):
                robot.publish_ism(key, np.full((20, 20), 240, np.uint8), resolution=0.05,
                                  origin=Pose2D(2.0 * n, 0.0))
            newest = robot.last_ism_id
            assert newest is not None and robot.offline_stats().sent == 3
            srv = start_server(tmp_path, {"zenoh": {"mode": "peer",
                                                    "listen": [free_tcp_endpoint()],
                                                    "connect": [router_ep]}})
            assert wait_until(lambda: bool(robot.servers(timeout=1.0)), 15)
            assert robot.settle_offline(10.0) == 0
            stats = robot.offline_stats()
            assert (stats.offered, stats.sent, stats.resent, stats.dropped_superseded,
                    stats.lost_in_flight) == (3, 1, 1, 2, 0), stats
            assert stats.offered == stats.sent + stats.held + stats.dropped
            robot.wait_fused([newest], timeout=10.0)  # the newest is in the map
            with srv.client() as direct:
                assert wait_processed(direct, 1).get("isms_fused", 0) == 1
                layer = ["robot1/laser/obstacle"]
                sent_again = direct.submap(x=4.5, y=0.5, width=1.0, height=1.0, layers=layer)
                superseded = direct.submap(x=0.5, y=0.5, width=1.0, height=1.0, layers=layer)
                assert sent_again.probabilities().min() > 0.9
                assert np.all(superseded.probabilities() == 0.5)
    finally:
        if srv is not None:
            assert srv.terminate() == 0
        stop(router)


def _listening(endpoint: str) -> bool:
    host, port = endpoint.removeprefix("tcp/").rsplit(":", 1)
    try:
        socket.create_connection((host, int(port)), timeout=0.5).close()
    except OSError:
        return False
    return True
