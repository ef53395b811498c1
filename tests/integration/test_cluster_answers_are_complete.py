"""A cluster's answers are complete: three members (``[cluster] enabled``, 2 replicas, each its
own store directory) behind ``sogm-service router``, and one plain server of another map name
fed the same ISMs.  Once ingestion has settled, a sub-map of the whole area at a coarser
resolution than the map's (the coarse path, which reads only the cells its warp interpolates
from), a fused window and the supercells of the area, asked through the router and through
each member by its id, equal the plain server's bit for bit: a member that does not own a
tile fetches it from its owners, and never answers it as unknown.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
import zenoh

from sogm_service.client.mapclient import MapClient
from sogm_service.client.session import free_tcp_endpoint
from sogm_service.core.geometry import Pose2D
from sogm_service.wire import codec
from sogm_service.wire.errors import ServiceError
from sogm_service.wire.keys import MapKeys
from sogm_service.wire.queries import GridReply, SupercellReply
from tests.conftest import ServerProcess, start_server, wait_until

pytestmark = [pytest.mark.integration, pytest.mark.slow]

RES = 0.25  # the ISMs' cells; the map keeps its default 5 cm cells and 256-cell tiles (12.8 m:
# 8 x 8 of them over the area, so every member lacks some), so a 0.5 m window is coarse
AREA = 100.0
N_ISMS = 60
LAYER = "r1/laser/obstacle"
WINDOW = dict(x=AREA / 2, y=AREA / 2, width=AREA, height=AREA, resolution=0.5)


def deterministic_isms(n: int = N_ISMS, seed: int = 11) -> list[tuple[np.ndarray, Pose2D]]:
    """``n`` 64 x 64 prob_u8 grids at 0.25 m spread over the 100 m x 100 m area (mild values:
    no cell reaches the clamp, so Eq. 1 is exact integer addition)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        origin = Pose2D(float(rng.integers(0, 336)) * RES, float(rng.integers(0, 336)) * RES, 0.0)
        out.append((rng.integers(60, 200, size=(64, 64), dtype=np.uint8), origin))
    return out


# fetch_timeout_s: a member fetching a whole area's tiles from two owners on a busy 2-core
# machine may wait more than the default second (then it fails the query with no_owner).
def member(tmp_path: Path, name: str, router: str, servers: int,
           sections: dict[str, dict[str, Any]] | None = None) -> ServerProcess:
    """A cluster member connected to the router (its own folder and store directory unless
    ``sections`` name another store)."""
    base: dict[str, dict[str, Any]] = {
        "cluster": {"enabled": True, "replicas": 2, "fetch_timeout_s": 5.0},
        "storage": {"directory": str(tmp_path / name / "tiles"), "checkpoint_interval_s": 1.0},
        "zenoh": {"listen": [free_tcp_endpoint()], "connect": [router]},
    }
    for k, v in (sections or {}).items():
        base[k] = {**base.get(k, {}), **v}
    (tmp_path / name).mkdir(exist_ok=True)
    return start_server(tmp_path / name, base, name=name, servers=servers, wait=60.0)


def plain_server(tmp_path: Path, router: str) -> ServerProcess:
    (tmp_path / "ref").mkdir(exist_ok=True)
    return start_server(tmp_path / "ref", {
        "map": {"name": "ref"},
        "zenoh": {"listen": [free_tcp_endpoint()], "connect": [router]}}, name="ref")


def member_stats(client: MapClient) -> dict[str, dict[str, Any]]:
    """Every member's stats by server id (one reply each: consolidation NONE)."""
    out = {}
    for reply in client.session.get(client.key("stats"), target=zenoh.QueryTarget.ALL,
                                    consolidation=zenoh.ConsolidationMode.NONE, timeout=5.0):
        if reply.ok is not None:
            got = msgpack.unpackb(reply.ok.payload.to_bytes())
            out[got["server_id"]] = got
    return out


def settled(client: MapClient, ref: MapClient, members: int, n: int) -> bool:
    stats = member_stats(client)
    return (len(stats) == members and ref.stats().counters.get("isms_fused", 0) >= n
            and all(s["counters"].get("isms_fused", 0) + s["counters"].get(
                "cluster_isms_elsewhere", 0) >= n and not s["extra"].get("cluster_handover")
                for s in stats.values()))


def served_tiles(client: MapClient) -> dict[str, set[tuple[int, int]]]:
    """The tiles each member serves itself, by member id (``cluster/held``)."""
    out = {}
    for reply in client.session.get(client.key("cluster", "held"), target=zenoh.QueryTarget.ALL,
                                    consolidation=zenoh.ConsolidationMode.NONE, timeout=5.0):
        if reply.ok is not None:
            got = msgpack.unpackb(reply.ok.payload.to_bytes())
            out[str(got["member"])] = {(int(i), int(j)) for i, j in got["tiles"]}
    return out


def supercells(client: MapClient, key: str, timeout: float = 120.0) -> list[Any]:
    """The SEVDS nodes of the whole area (asked again while the server compiles its kernels)."""
    params = {**WINDOW, "layers": [LAYER]}
    deadline = time.monotonic() + timeout
    while True:
        try:
            return list(codec.decode(SupercellReply, client.get_raw(key, params,
                                                                    timeout=30.0)).nodes)
        except ServiceError as exc:
            if exc.code != "warming_up" or time.monotonic() > deadline:
                raise
            time.sleep(0.5)


def unknown_where_known(got: np.ndarray, want: np.ndarray) -> int:
    return int(np.count_nonzero((got == 0) & (want != 0)))


def window(client: MapClient, key: str | None = None, name: str = "submap") -> np.ndarray:
    """The whole area at 0.5 m as fixed log-odds, through the router or one member's key."""
    params = {**WINDOW, "encoding": "logodds_i16"}
    if name == "fused":
        params["layers"] = [LAYER]
    key = key or client.key(name)
    return np.asarray(codec.decode(GridReply, client.get_raw(key, params, timeout=10.0))
                      .data.array())


@pytest.mark.timeout(240)
def test_a_sub_map_through_any_member_is_the_single_servers(tmp_path: Path, router: str,
                                                           procs: list[ServerProcess]) -> None:
    for k, name in enumerate("abc"):
        procs.append(member(tmp_path, name, router, servers=k + 1))
    procs.append(plain_server(tmp_path, router))
    with MapClient.connect(router, timeout=5.0) as robot, \
            MapClient.connect(router, map_name="ref", timeout=5.0) as ref:
        assert wait_until(lambda: len(member_stats(robot)) == 3, 30)
        for k, (grid, origin) in enumerate(deterministic_isms()):
            robot.publish_ism("ism/r1/laser/obstacle", grid, resolution=RES, origin=origin,
                              stamp=1000.0 + k)
        assert wait_until(lambda: settled(robot, ref, 3, N_ISMS), 60), member_stats(robot)
        want = window(ref)
        assert np.count_nonzero(want) > 0.5 * want.size  # the ISMs cover most of the area
        got = window(robot)  # through the router: one member computes it
        assert np.array_equal(got, want), f"{unknown_where_known(got, want)} cells unknown"
        keys = MapKeys(robot.prefix, robot.map_name)
        held = served_tiles(robot)
        every = set().union(*held.values())
        for server_id in member_stats(robot):
            assert held[server_id] < every  # it lacks tiles the others serve
            got = window(robot, keys.member(server_id, "submap"))
            assert np.array_equal(got, want), \
                f"{server_id}: {unknown_where_known(got, want)} cells unknown"
        fused_want = window(ref, name="fused")
        for server_id in member_stats(robot):
            assert np.array_equal(window(robot, keys.member(server_id, "fused"), "fused"),
                                  fused_want)
        nodes = supercells(ref, ref.key("supercells"))
        assert len(nodes) > 10
        assert supercells(robot, robot.key("supercells")) == nodes
        for server_id in member_stats(robot):
            assert supercells(robot, keys.member(server_id, "supercells")) == nodes
