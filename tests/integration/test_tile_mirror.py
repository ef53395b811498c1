"""A mirror of a region pulls through ``tiles/changed`` only the tiles whose version moved,
counted in replies and bytes, holds the server's tiles bit for bit, and keeps its copy across a
restart of a server with a store (versions persist in the tile header)."""

from __future__ import annotations

from pathlib import Path

import msgpack
import numpy as np
import pytest
import zenoh

from sogm_service.client import MapClient, Pose2D, ServiceError
from sogm_service.client.mirror import TileMirror
from sogm_service.client.session import loopback_settings, open_session
from sogm_service.wire.tilefile import tile_from_bytes
from tests.conftest import ServerProcess, start_server, wait_until

pytestmark = pytest.mark.integration

RES, T = 0.1, 64
SPAN = RES * T  # 6.4 m
KEY = "ism/r1/laser/obstacle"
LAYER = "r1/laser/obstacle"


def sections(store: Path, endpoint: str | None = None) -> dict[str, dict[str, object]]:
    out: dict[str, dict[str, object]] = {
        "map": {"resolution": RES, "tile_size": T},
        "storage": {"directory": str(store), "checkpoint_interval_s": 60.0}}
    if endpoint is not None:
        out["zenoh"] = {"listen": [endpoint]}
    return out


def put(client: MapClient, i: int, j: int, value: int) -> None:
    """A 20 x 20-cell ISM inside tile ``(i, j)`` (occupancy percent; -1 = unknown)."""
    client.publish_ism(KEY, np.full((20, 20), value, np.int8), resolution=RES,
                       origin=Pose2D(i * SPAN + 1.0, j * SPAN + 1.0, 0.0), wait=True)


def assert_same_as_server(client: MapClient, mirror: TileMirror) -> None:
    for (i, j), held in mirror.tiles.items():
        server = tile_from_bytes(client.tiles(i, j)[(i, j)])
        assert held.version == server.header.tile_version > 0
        assert sorted(held.planes) == sorted(server.header.layers)
        for k, name in enumerate(server.header.layers):
            assert held.plane(name).tobytes() == server.data[k].tobytes()


def served(client: MapClient) -> int:
    return int(client.stats().counters.get("tiles_changed_served", 0))


def test_refresh_pulls_exactly_the_changed_tiles_and_survives_a_restart(tmp_path: Path) -> None:
    store = tmp_path / "store"
    srv = start_server(tmp_path, sections(store))
    second: ServerProcess | None = None
    try:
        with srv.client() as client:
            for i, j in [(0, 0), (1, 0), (2, 1)]:
                put(client, i, j, 80)
            mirror = client.mirror(x=2 * SPAN, y=2 * SPAN, width=4 * SPAN, height=4 * SPAN)
            assert mirror.bounds == (0, 0, 3, 3)

            first = mirror.refresh()  # a late joiner: everything of the region
            assert sorted(first) == [(0, 0), (1, 0), (2, 1)]
            assert mirror.last.replies == 3
            whole = sum(len(client.tiles(i, j)[(i, j)]) for i, j in first)
            # Each tile's header says when it was written (a float whose digits vary): the same
            # tile, asked twice, may differ by a few bytes; a second tile would be ~480 more.
            assert abs(mirror.last.bytes - whole) <= 8 * len(first)
            assert_same_as_server(client, mirror)

            put(client, 1, 0, 20)  # one tile changes
            assert mirror.refresh() == [(1, 0)]
            assert mirror.last.replies == 1
            assert abs(mirror.last.bytes - len(client.tiles(1, 0)[(1, 0)])) <= 8
            assert_same_as_server(client, mirror)

            assert mirror.refresh() == []  # nothing new: nothing pulled
            assert (mirror.last.replies, mirror.last.bytes) == (0, 0)
            put(client, 2, 1, -1)  # all unknown: the content does not change
            assert mirror.refresh() == []
            assert mirror.last.bytes == 0
            held = mirror.versions()
            print(f"tiles/changed: first refresh {whole} bytes in 3 replies, one tile "
                  f"{len(client.tiles(1, 0)[(1, 0)])} bytes, nothing new 0 bytes")

        srv.terminate()  # SIGTERM flushes every tile, with its version, to the store
        second = start_server(tmp_path, sections(store, srv.endpoint), name="again")
        with second.client() as client:
            again = client.mirror(x=2 * SPAN, y=2 * SPAN, width=4 * SPAN, height=4 * SPAN)
            again.tiles = dict(mirror.tiles)  # what the device kept
            assert again.refresh() == []  # the versions survived: nothing re-pulled
            assert again.last.bytes == 0 and served(client) == 0
            assert again.versions() == held
            assert_same_as_server(client, again)
            put(client, 0, 0, 90)
            assert again.refresh() == [(0, 0)] and again.versions()[(0, 0)] > held[(0, 0)]
    finally:
        for proc in (srv, second):
            if proc is not None and proc.proc.poll() is None:
                proc.terminate()


def _changed(session: zenoh.Session, key: str, body: dict[str, object],
             any_key: bool = True) -> list[zenoh.Reply]:
    return list(session.get(key, payload=msgpack.packb(body), timeout=5.0,
                            accept_replies=zenoh.ReplyKeyExpr.ANY if any_key
                            else zenoh.ReplyKeyExpr.MATCHING_QUERY))


def test_bad_requests_are_refused_with_a_code_and_change_nothing(tmp_path: Path) -> None:
    srv = start_server(tmp_path, {"map": {"resolution": RES, "tile_size": T}})
    try:
        with srv.client() as client:
            put(client, 0, 0, 80)
            key = client.key("tiles", "changed")
            session = open_session(loopback_settings(connect=srv.endpoint, mode="client"))
            try:
                cases = [
                    ({"i0": 0, "j0": 0, "i1": 0, "j1": 0}, False, "bad_parameter"),
                    ({"i0": 0, "j0": 0, "i1": 10**6, "j1": 10**6}, True, "window_too_large"),
                    ({"width": 1e5, "height": 1e5}, True, "window_too_large"),
                    ({"x": 1e12, "width": 1.0, "height": 1.0}, True, "out_of_world"),
                    ({"i0": 0}, True, "bad_parameter"),
                    ({"i0": 0, "j0": 0, "i1": 0, "j1": 0, "held": {"zero": 1}}, True,
                     "bad_parameter"),
                    ({"i0": 0, "j0": 0, "i1": 0, "j1": 0,
                      "held": [[k, 0, 1] for k in range(2000)]}, True, "window_too_large"),
                ]
                for body, any_key, code in cases:
                    replies = _changed(session, key, body, any_key)
                    assert [r.ok for r in replies if r.ok is not None] == []
                    errors = [msgpack.unpackb(r.err.payload.to_bytes()) for r in replies
                              if r.err is not None]
                    assert [e["code"] for e in errors] == [code], body
                # a plain session's well-formed ask: one reply, the tile, keyed by its index
                ok = _changed(session, key, {"i0": 0, "j0": 0, "i1": 1, "j1": 1})
                assert [str(r.ok.key_expr) for r in ok if r.ok is not None] == [
                    client.key("tiles", "0", "0")]
                assert [str(r.ok.encoding) for r in ok if r.ok is not None] == [
                    "application/x-sogm-tile"]
                # tiles/** still answers whole tiles only, not this queryable
                assert list(client.tiles()) == [(0, 0)]
            finally:
                session.close()
            counters = client.stats().counters
            assert counters.get("query_errors_window_too_large", 0) == 3
            assert wait_until(lambda: client.stats().counters.get("isms_fused", 0) == 1)
            with pytest.raises(ServiceError):
                client.mirror(x=0.0, y=0.0, width=1e5, height=1e5).refresh()
    finally:
        srv.terminate()
