"""Admission before work, through a real server: hostile but valid ISMs and poses are refused
from their header with their code, the map stays bit-identical, and the server's memory stays
bounded."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from sogm_service.client.mapclient import MapClient
from sogm_service.core.geometry import Pose2D
from sogm_service.wire import codec
from sogm_service.wire.errors import ISM_CODES, POSE_CODES
from sogm_service.wire.messages import IsmMessage, PoseModel
from tests.conftest import ServerProcess, start_server, wait_processed, wait_until

pytestmark = pytest.mark.integration

RSS_BOUND_MB = 64
"""The most a burst of hostile input may grow the server's RSS (the issue saw 3.57 GB from one
64 km ISM and 1 GB from 8 ISMs of 961 tiles each)."""

LIMITS = {"world_extent_m": 10_000.0, "max_layers": 2, "max_robots": 2,
          "max_robot_name": 32, "max_layer_name": 32}


def baseline_rss_mb(client: MapClient, pid: int) -> float:
    """The server's RSS once its start-up is over: the SEVDS kernels are compiled or loaded
    in the background at start (LLVM's tens of MB), not by the input under test."""
    assert wait_until(lambda: client.stats().extra.get("kernels_ready") is True, 60.0)
    return rss_mb(pid)


def rss_mb(pid: int) -> float:
    """VmRSS of a process we started, in MB (Linux /proc)."""
    text = Path(f"/proc/{pid}/status").read_text()
    match = re.search(r"^VmRSS:\s+(\d+) kB", text, re.MULTILINE)
    assert match is not None
    return int(match.group(1)) / 1024


def ism(resolution: float = 0.05, width: int = 1, height: int = 1, x: float = 0.0,
        y: float = 0.0, yaw: float = 0.0, layer: str = "obstacle",
        robot: str | None = None, value: int = 230) -> bytes:
    data = np.full((height, width), value, dtype=np.uint8)
    return codec.encode(IsmMessage(layer=layer, robot=robot, resolution=resolution,
                                   origin=PoseModel(x=x, y=y, yaw=yaw), width=width,
                                   height=height, encoding="prob_u8", data=data.tobytes()))


def snapshot(client: MapClient) -> bytes:
    """The seeded area's log-odds, raw (bit-identical comparison)."""
    return client.submap(x=1.0, y=1.0, width=12.0, height=12.0, encoding="logodds_i16").data \
        .tobytes()


@pytest.fixture
def seeded(tmp_path: Path) -> ServerProcess:
    srv = start_server(tmp_path, {"limits": LIMITS, "storage": {"memory_budget_mb": 1.0}})
    with srv.client() as c:
        grid = np.random.default_rng(7).integers(0, 256, (80, 80), dtype=np.uint8)
        c.publish_ism("ism/r1/obstacle", grid, resolution=0.1, origin=Pose2D(-2.0, -2.0, 0.3),
                      robot="r1", layer="obstacle")
        counters = wait_processed(c, 1)
        assert counters.get("isms_fused") == 1
    yield srv
    if srv.proc.poll() is None:
        srv.terminate()


HOSTILE: list[tuple[str, str, bytes]] = [
    # one cell of 4 km: ~96,000 tiles inside this 10 km world (the issue's 64 km cell is
    # tested against the default world below)
    ("too_large", "ism/r1/obstacle", ism(resolution=4000.0, x=-2000.0, y=-2000.0)),
    ("out_of_world", "ism/r1/obstacle", ism(resolution=64_000.0, x=-5000.0, y=-5000.0)),
    ("out_of_world", "ism/r1/obstacle", ism(x=1e25, y=1e25)),
    ("out_of_world", "ism/r1/obstacle", ism(x=1e300, robot="r1")),
    ("out_of_world", "ism/r1/obstacle", ism(resolution=1e300)),
    ("out_of_world", "ism/r1/obstacle", ism(x=9_999.99, resolution=1.0, width=2)),
    ("too_many_layers", "ism/r1/third", ism(layer="third")),  # beyond max_layers = 2
    ("bad_layer", "ism/r1/obstacle", ism(layer="L" * 100_000)),  # the pattern's 128 chars
    ("name_too_long", "ism/r1/obstacle", ism(layer="L" * 100)),  # max_layer_name = 32
    ("name_too_long", "ism/" + "R" * 40 + "/obstacle", ism(robot="R" * 40)),
    # 50 m at 0.5 m: ~25 new tiles of 131 kB over a 1 MB budget without a store
    ("memory_budget", "ism/r1/obstacle", ism(resolution=0.5, width=100, height=100, x=100.0)),
]


def test_hostile_isms_are_refused_with_their_code_and_change_nothing(
        seeded: ServerProcess) -> None:
    with seeded.client() as c:
        # a second layer fills max_layers = 2; a third is hostile
        c.publish_raw("ism/r1/second", ism(layer="second"))
        wait_processed(c, 2)
        before, info_before = snapshot(c), c.info()
        assert info_before.layers == ["obstacle", "second"]
        for _, key, payload in HOSTILE:
            c.publish_raw(key, payload)
        counters = wait_processed(c, 2 + len(HOSTILE))
        stats = c.stats()
        assert counters["isms_fused"] == 2, stats.rejected
        expected: dict[str, int] = {}
        for code, _, _ in HOSTILE:
            expected[code] = expected.get(code, 0) + 1
        assert stats.rejected == expected, stats.rejected
        assert stats.extra["reserved_mb"] == 0.0  # every admitted ISM's reservation released
        assert set(expected) <= set(ISM_CODES) | {"bad_layer"}
        assert snapshot(c) == before
        info = c.info()  # info, robots, stats all still answer
        assert info.tiles == info_before.tiles and info.bounds == info_before.bounds
        assert [e.robot for e in c.robots().robots] == ["r1"]
    assert seeded.terminate() == 0
    log = seeded.log()
    assert "L" * 300 not in log  # attacker strings are cut in log lines
    assert max(len(line) for line in log.splitlines()) < 1000


def test_a_third_layer_is_refused_but_the_second_is_fused(seeded: ServerProcess) -> None:
    with seeded.client() as c:
        c.publish_raw("ism/r1/a", ism(layer="a"))
        c.publish_raw("ism/r1/b", ism(layer="b"))
        counters = wait_processed(c, 3)
        assert counters["isms_fused"] == 2
        assert c.stats().rejected == {"too_many_layers": 1}
        assert c.info().layers == ["obstacle", "a"]


def test_robots_beyond_the_limit_are_refused_poses_and_isms(seeded: ServerProcess) -> None:
    with seeded.client() as c:
        c.publish_pose("r2", 1.0, 1.0)  # r1 (from its ISM) and r2: the limit of 2
        assert wait_until(lambda: len(c.robots().robots) == 2)
        before = snapshot(c)
        c.publish_raw("ism/r3/obstacle", ism(robot="r3"))
        c.publish_pose("r4", 1.0, 1.0)
        c.publish_pose("r2", 1e300, 0.0)  # out of the world: r2 stays where it was
        wait_processed(c, 2)
        assert wait_until(lambda: c.stats().counters.get("poses_rejected", 0) == 2)
        stats = c.stats()
        assert stats.rejected == {"too_many_robots": 1}
        assert stats.counters["poses_rejected_too_many_robots"] == 1
        assert stats.counters["poses_rejected_out_of_world"] == 1
        assert {"too_many_robots", "out_of_world"} <= set(POSE_CODES)
        robots = {e.robot: (e.i, e.j) for e in c.robots().robots}
        assert robots == {"r1": robots["r1"], "r2": (0, 0)}
        assert snapshot(c) == before


def test_rss_stays_bounded_under_a_burst_of_hostile_isms(seeded: ServerProcess) -> None:
    pid = seeded.proc.pid
    with seeded.client() as c:
        c.publish_raw("ism/r1/obstacle", ism(resolution=64_000.0))  # warm every code path
        wait_processed(c, 2)
        before_rss, before = baseline_rss_mb(c, pid), snapshot(c)
        burst = [payload for _, key, payload in HOSTILE if key == "ism/r1/obstacle"]
        n = 0
        for k in range(40):
            for payload in burst:
                c.publish_raw("ism/r1/obstacle", payload)
                n += 1
            # 961-tile ISMs of the issue (1 GB after 8): refused by too_large, never built
            c.publish_raw("ism/r1/obstacle", ism(resolution=400.0, x=-6000.0 + k))
            n += 1
        counters = wait_processed(c, 2 + n, timeout=60)
        assert counters["isms_fused"] == 1 and counters["isms_rejected"] == 1 + n
        grown = rss_mb(pid) - before_rss
        assert grown < RSS_BOUND_MB, f"RSS grew by {grown:.1f} MB"
        assert snapshot(c) == before


def test_the_issues_64km_ism_is_refused_as_too_large_in_the_default_world(
        tmp_path: Path) -> None:
    srv = start_server(tmp_path)
    try:
        with srv.client() as c:
            before = baseline_rss_mb(c, srv.proc.pid)
            payload = ism(resolution=64_000.0)
            assert len(payload) < 200  # the issue's 132-byte message
            for _ in range(20):
                c.publish_raw("ism/r1/obstacle", payload)
            counters = wait_processed(c, 20)
            assert counters.get("isms_fused", 0) == 0
            assert c.stats().rejected == {"too_large": 20}
            assert c.info().tiles == []
            assert rss_mb(srv.proc.pid) - before < RSS_BOUND_MB
    finally:
        srv.terminate()
