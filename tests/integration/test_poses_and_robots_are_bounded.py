"""Bounds of a real server: poses coalesced latest-per-robot and every one counted;
robot names bounded; a second server on a locked store says so in one line and exits 2."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import zenoh

from sogm_service.wire import codec
from sogm_service.wire.messages import PoseMessage
from tests.conftest import start_server, wait_until
from tests.integration.test_hostile_isms_are_refused import RSS_BOUND_MB, baseline_rss_mb, rss_mb

pytestmark = pytest.mark.integration

ROBOTS = 200
POSES_PER_ROBOT = 50
SPAN = 256 * 0.05  # default tile edge (m)


def test_a_pose_flood_is_coalesced_and_every_pose_counted(tmp_path: Path) -> None:
    """received == applied + coalesced + rejected, and each robot ends where its last pose is
    (a small ``max_pending_poses`` so that a backlog is coalesced rather than queued)."""
    srv = start_server(tmp_path, {"limits": {"max_pending_poses": 64}})
    try:
        with srv.client() as c:
            before = baseline_rss_mb(c, srv.proc.pid)
            pubs = {f"r{k}": c.session.declare_publisher(
                f"pose/r{k}", congestion_control=zenoh.CongestionControl.BLOCK)
                for k in range(ROBOTS)}
            for n in range(POSES_PER_ROBOT):
                last = n == POSES_PER_ROBOT - 1
                for k in range(ROBOTS):
                    # the last pose of robot k is the centre of tile (k, 0); earlier ones wander
                    x = (k + 0.5) * SPAN if last else float(n % 7) * 3.1
                    pubs[f"r{k}"].put(codec.encode(PoseMessage(robot=f"r{k}", x=x, y=6.4,
                                                               stamp=float(n))))
            total = ROBOTS * POSES_PER_ROBOT

            def settled() -> bool:
                cnt = c.stats().counters
                done = (cnt.get("poses_applied", 0) + cnt.get("poses_coalesced", 0)
                        + cnt.get("poses_rejected", 0))
                return cnt.get("poses_received", 0) == total and done == total

            assert wait_until(settled, timeout=60), c.stats().counters
            counters = c.stats().counters
            assert counters.get("poses_rejected", 0) == 0
            robots = {e.robot: (e.i, e.j) for e in c.robots().robots}
            assert robots == {f"r{k}": (k, 0) for k in range(ROBOTS)}  # the latest won
            assert rss_mb(srv.proc.pid) - before < RSS_BOUND_MB
    finally:
        srv.terminate()


def test_long_robot_names_and_far_poses_are_refused_and_counted(tmp_path: Path) -> None:
    srv = start_server(tmp_path, {"limits": {"max_robot_name": 16}})
    try:
        with srv.client() as c:
            c.publish_pose("R" * 200, 1.0, 1.0)
            c.publish_pose("ok", 1e300, 1.0)
            c.publish_pose("ok", 1.0, 1.0)
            assert wait_until(lambda: c.stats().counters.get("poses_applied", 0) == 1)
            counters = c.stats().counters
            assert counters["poses_received"] == 3 and counters["poses_rejected"] == 2
            assert counters["poses_rejected_name_too_long"] == 1
            assert counters["poses_rejected_out_of_world"] == 1
            assert [e.robot for e in c.robots().robots] == ["ok"]  # robots still answers
    finally:
        srv.terminate()


def test_second_server_on_a_locked_store_prints_one_line_and_exits_2(tmp_path: Path) -> None:
    store = tmp_path / "store"
    srv = start_server(tmp_path, {"storage": {"directory": str(store)}})
    try:
        proc = subprocess.run([sys.executable, "-m", "sogm_service", "serve", "--config",
                               str(srv.config_path)], capture_output=True, text=True,
                              timeout=60)
        assert proc.returncode == 2
        lines = [line for line in proc.stderr.splitlines() if line.strip()]
        assert len(lines) == 1, proc.stderr
        assert str(store) in lines[0] and f"pid {srv.proc.pid}" in lines[0]
        assert "Traceback" not in proc.stderr + proc.stdout
    finally:
        assert srv.terminate() == 0
