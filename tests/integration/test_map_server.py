"""The map server over real Zenoh sessions: a server process and client sessions on loopback."""

from __future__ import annotations

import math
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest

from sogm_service.client.mapclient import MapClient
from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice
from sogm_service.core.map.tiles import TiledMap
from sogm_service.service.server import pipeline as ingest
from sogm_service.service.server import queries
from sogm_service.wire import codec
from sogm_service.wire.errors import QueryTimeoutError, ServiceError
from sogm_service.wire.messages import IsmMessage, PoseMessage, PoseModel
from sogm_service.wire.queries import FusedRequest, SubmapRequest
from tests.conftest import ServerProcess, start_server, wait_processed, wait_until
from tests.unit.core.test_logodds import HI, LO
from tests.unit.wire.test_codec import ism_payload

pytestmark = pytest.mark.integration


def _ism(data: np.ndarray, res: float, origin: Pose2D, encoding: str) -> IsmMessage:
    return IsmMessage(resolution=res, origin=PoseModel(x=origin.x, y=origin.y, yaw=origin.yaw),
                      width=data.shape[1], height=data.shape[0], encoding=encoding,
                      data=np.ascontiguousarray(data).tobytes())


def test_two_robots_fuse_into_their_layers_and_match_the_core(server: ServerProcess) -> None:
    rng = np.random.default_rng(7)
    obstacle = rng.integers(0, 101, (80, 120)).astype(np.int8)
    obstacle[:10] = -1  # unknown rows must not touch the map
    floor = rng.random((40, 50)).astype(np.float32)
    isms = [
        ("ism/robot1/laser/obstacle", _ism(obstacle, 0.05, Pose2D(1.0, -0.5, 0.0),
                                            "occupancy_i8")),
        ("ism/robot2/camera/floor", _ism(floor, 0.1, Pose2D(2.0, 1.0, 0.4), "prob_f32")),
        ("ism/robot1/laser/obstacle", _ism(obstacle, 0.05, Pose2D(1.0, -0.5, 0.0),
                                            "occupancy_i8")),
    ]
    with server.client() as robot1, server.client() as robot2, server.client() as viewer:
        for key, msg in isms:
            (robot1 if "robot1" in key else robot2).publish_raw(key, codec.encode(msg))
        counters = wait_processed(viewer, len(isms))
        assert counters.get("isms_fused") == 3

        info = viewer.info()
        assert sorted(info.layers) == ["robot1/laser/obstacle", "robot2/camera/floor"]

        # The same ISMs fused by the core directly, in the same order.
        local = TiledMap("default", "map", TileLattice(0.05, 256))
        for key, msg in isms:
            ingest.fuse_ism(local, msg, ingest.layer_name(msg, key, "ism/**"))
        # Two sessions publish, so the layers' order at the server is their arrival order: ask
        # for both by name (the order of the reply follows the request).
        window = dict(x=3.0, y=1.0, yaw=0.3, width=6.0, height=5.0, resolution=0.04,
                      layers=["robot1/laser/obstacle", "robot2/camera/floor"])
        got = viewer.submap(**window, encoding="logodds_i16")
        want = queries.submap(local, SubmapRequest(**window, encoding="logodds_i16"), 0.0)
        assert got.layers == want.layers
        np.testing.assert_array_equal(got.data, want.data.array())

        for method in ("bayes", "max"):
            got_f = viewer.fused(method=method, **window, encoding="logodds_i16")
            want_f = queries.fused(local, FusedRequest(**window, method=method,
                                                       encoding="logodds_i16"), 0.0)
            np.testing.assert_array_equal(got_f.data, want_f.data.array())

        stats = viewer.stats()
        assert stats.counters["queries_submap"] == 1
        assert stats.counters["queries_fused"] == 2
        assert "submap" in stats.latency_ms and stats.latency_ms["submap"]["p50"] > 0


def test_rotated_rescaled_ism_lands_where_geometry_says(server: ServerProcess) -> None:
    # A 40x40 ISM at 10 cm, rotated 30 degrees, unknown except one occupied 3x3 block.
    data = np.full((40, 40), -1, np.int8)
    data[25:28, 10:13] = 95
    origin = Pose2D(4.0, 3.0, math.radians(30))
    block_centre = origin.transform_points(np.array([11.5 * 0.1, 26.5 * 0.1]))
    with server.client() as client:
        client.publish_ism("ism/r/laser/obstacle", data, resolution=0.1, origin=origin)
        wait_processed(client, 1)
        sub = client.submap(x=5.0, y=5.0, width=8.0, height=8.0, resolution=0.05,
                            interp="nearest")
    p = sub.probabilities()[0]
    occupied = np.argwhere(p > 0.9)
    assert occupied.size > 0
    rows, cols = occupied[:, 0], occupied[:, 1]
    centre_cell = np.array([cols.mean(), rows.mean()])
    centre_world = sub.geometry.cell_to_world()[:2] @ np.array([*centre_cell, 1.0])
    assert np.linalg.norm(centre_world - block_centre) < 0.05  # within one map cell
    # The 0.3 x 0.3 m block is 36 cells at 5 cm; biodds fusion blends its edge with the
    # surrounding unknown, so evidence reaches at most half a source cell (5 cm) further.
    evidence = np.abs(p - 0.5) > 1e-3
    assert 30 <= np.count_nonzero(evidence) <= (0.4 / 0.05) ** 2 + 4
    # Everything the ISM called unknown stays unknown: no cell turned free.
    assert (p[evidence] > 0.5).all()


BAD_PAYLOADS = {
    "malformed_msgpack": b"\xc1\xff\x00",
    "not_a_map": msgpack.packb([1, 2, 3]),
    "missing_field": msgpack.packb({"width": 2, "height": 2, "encoding": "prob_u8",
                                    "data": b"1234"}),
    "wrong_type": msgpack.packb({"resolution": 0.1, "width": "2", "height": 2,
                                 "encoding": "prob_u8", "data": b"1234"}),
    "data_length": msgpack.packb({"resolution": 0.1, "width": 2, "height": 2,
                                  "encoding": "prob_u8", "data": b"123"}),
    "non_finite": msgpack.packb({"resolution": 0.1, "width": 1, "height": 1,
                                 "encoding": "prob_f32",  # NaN is "unknown" since v2
                                 "data": np.array([np.inf], np.float32).tobytes()}),
    "non_positive_resolution": msgpack.packb({"resolution": 0.0, "width": 2, "height": 2,
                                              "encoding": "prob_u8", "data": b"1234"}),
    "out_of_range": msgpack.packb({"resolution": 0.1, "width": 2, "height": 1,
                                   "encoding": "occupancy_i8",
                                   "data": np.array([50, 101], np.int8).tobytes()}),
    "too_large": msgpack.packb({"resolution": 0.1, "width": 5000, "height": 5000,
                                "encoding": "prob_u8", "data": b"\x00" * 25_000_000}),
    "wrong_frame": codec.encode(IsmMessage(frame="odom", resolution=0.1, width=1, height=1,
                                           encoding="prob_u8", data=b"\xff")),
}


def test_bad_isms_are_rejected_counted_and_leave_the_map_unchanged(tmp_path: Path) -> None:
    srv = start_server(tmp_path, {"limits": {"max_ism_cells": 1_000_000}})
    try:
        with srv.client() as client:
            good = np.full((50, 50), 200, np.uint8)
            client.publish_ism("ism/r/laser/obstacle", good, resolution=0.05)
            wait_processed(client, 1)
            before = client.submap(x=1, y=1, width=4, height=4, encoding="logodds_i16")
            for payload in BAD_PAYLOADS.values():
                client.publish_raw("ism/r/laser/obstacle", payload)
            counters = wait_processed(client, 1 + len(BAD_PAYLOADS))
            stats = client.stats()
            after = client.submap(x=1, y=1, width=4, height=4, encoding="logodds_i16")
        assert counters["isms_rejected"] == len(BAD_PAYLOADS)
        for reason in BAD_PAYLOADS:
            assert stats.rejected.get(reason) == 1, (reason, stats.rejected)
        np.testing.assert_array_equal(before.data, after.data)
        assert srv.proc.poll() is None  # still serving
    finally:
        assert srv.terminate() == 0
    assert "rejected ISM [malformed_msgpack]" in srv.log()


@pytest.mark.parametrize(("params", "code", "parameter"), [
    ({"interp": "cubic"}, "bad_parameter", "interp"),
    ({"width": "-3"}, "bad_parameter", "width"),
    ({"x": "nan"}, "bad_parameter", "x"),
    ({"frobnicate": "1"}, "bad_parameter", "frobnicate"),
    ({"layers": "nope"}, "unknown_layer", "layers"),
    ({"width": "100000", "height": "100000"}, "window_too_large", "width"),
])
def test_bad_query_parameters_get_an_error_naming_them(
        server: ServerProcess, params: dict[str, str], code: str, parameter: str) -> None:
    with server.client() as client:
        client.publish_ism("ism/r/laser/obstacle", np.full((4, 4), 200, np.uint8),
                           resolution=0.05)
        wait_processed(client, 1)
        with pytest.raises(ServiceError) as err:
            client.get_raw(client.key("submap"), params)
    assert err.value.code == code
    assert err.value.parameter == parameter


def test_query_to_a_missing_map_times_out_with_a_typed_error(server: ServerProcess) -> None:
    with MapClient.connect(server.endpoint, map_name="nosuchmap", timeout=0.5) as client, \
            pytest.raises(QueryTimeoutError):
        client.info()


def test_liveliness_token_names_the_server(server: ServerProcess) -> None:
    with server.client() as client:
        ids = client.servers()
        assert ids == [client.info().server_id]


def test_sigterm_drains_the_queue_and_exits_zero(tmp_path: Path) -> None:
    srv = start_server(tmp_path)
    with srv.client() as client:
        for k in range(20):
            client.publish_ism(f"ism/r{k % 2}/laser/obstacle",
                               np.full((256, 256), 180, np.uint8), resolution=0.05)
    started = time.monotonic()
    assert srv.terminate(timeout=15) == 0
    assert time.monotonic() - started < 8.0
    assert "shutting down" in srv.log()


def test_latest_policy_counts_what_it_drops(tmp_path: Path) -> None:
    srv = start_server(tmp_path, {"limits": {"queue_policy": "latest"}})
    try:
        with srv.client() as client:
            for _ in range(30):
                client.publish_ism("ism/r/laser/obstacle",
                                   np.full((512, 512), 180, np.uint8), resolution=0.05)
            stats = wait_processed_or_dropped(client, 30)
        c = stats.counters
        assert c["isms_received"] == 30
        assert c.get("isms_fused", 0) + c.get("isms_dropped_latest", 0) == 30
        assert c.get("isms_fused", 0) >= 1
    finally:
        assert srv.terminate() == 0


def wait_processed_or_dropped(client: MapClient, n: int, timeout: float = 15.0):  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    while True:
        stats = client.stats()
        c = stats.counters
        done = c.get("isms_fused", 0) + c.get("isms_rejected", 0) + c.get(
            "isms_dropped_latest", 0)
        if done >= n or time.monotonic() > deadline:
            return stats
        time.sleep(0.05)


def test_unknown_cells_are_a_no_op_over_the_wire(server: ServerProcess) -> None:
    with server.client() as client:
        client.publish_ism("ism/r/laser/obstacle", np.full((10, 10), 100, np.int8),
                           resolution=0.1)
        wait_processed(client, 1)
        before = client.submap(x=0.5, y=0.5, width=1, height=1, resolution=0.1,
                               encoding="logodds_i16")
        client.publish_ism("ism/r/laser/obstacle", np.full((10, 10), -1, np.int8),
                           resolution=0.1)
        wait_processed(client, 2)
        after = client.submap(x=0.5, y=0.5, width=1, height=1, resolution=0.1,
                              encoding="logodds_i16")
    np.testing.assert_array_equal(before.data, after.data)
    _, hi = logodds.clamp_limits()
    assert before.data.min() > 0 and before.data.max() <= hi


def test_grid_reply_geometry_places_the_window(server: ServerProcess) -> None:
    with server.client() as client:
        client.publish_ism("ism/r/laser/obstacle", np.full((10, 10), 250, np.uint8),
                           resolution=0.1)
        wait_processed(client, 1)
        sub = client.submap(x=2.0, y=-1.0, yaw=0.5, width=3.0, height=2.0, resolution=0.1)
    g: GridGeometry = sub.geometry
    assert (g.width, g.height) == (30, 20)
    centre = g.cell_to_world()[:2] @ np.array([14.5, 9.5, 1.0])
    np.testing.assert_allclose(centre, [2.0, -1.0], atol=1e-9)
    assert g.origin.yaw == pytest.approx(0.5)


def test_ism_covering_absurd_ground_is_refused_before_any_tile_exists(
        server: ServerProcess) -> None:
    # Valid on the wire, but 100 m cells x 100 x 100 would create ~3.7 million tiles.
    with server.client() as client:
        client.publish_ism("ism/r/laser/obstacle", np.full((100, 100), 200, np.uint8),
                           resolution=100.0)
        wait_processed(client, 1)
        stats = client.stats()
        info = client.info()
    assert stats.rejected == {"too_large": 1}
    assert info.tiles == [] and info.layers == []


def test_payload_over_the_byte_limit_is_refused_before_queueing(tmp_path: Path) -> None:
    srv = start_server(tmp_path, {"limits": {"max_payload_bytes": 10_000}})
    try:
        with srv.client() as client:
            client.compression = None  # the limit is on the bytes that arrive: send them raw
            client.publish_ism("ism/r/laser/obstacle", np.full((200, 200), 200, np.uint8),
                               resolution=0.05)
            client.publish_ism("ism/r/laser/obstacle", np.full((50, 50), 200, np.uint8),
                               resolution=0.05)
            counters = wait_processed(client, 2)
            stats = client.stats()
    finally:
        assert srv.terminate() == 0
    assert counters["isms_fused"] == 1
    assert stats.rejected == {"too_large": 1}


def test_a_message_naming_another_robot_than_its_key_is_refused(server: ServerProcess) -> None:
    """Access control grants keys per robot, so the robot named in a payload must be the key's."""
    grid = np.full((20, 20), 230, np.uint8)
    with server.client() as client:
        client.publish_ism("ism/robotA/laser/obstacle", grid, resolution=0.05, robot="robotB")
        client.publish_raw("pose/robotA", codec.encode(PoseMessage(robot="robotB", x=30.0,
                                                                   y=30.0)))
        client.publish_ism("ism/robotA/laser/obstacle", grid, resolution=0.05, robot="robotA")
        client.publish_pose("robotA", 1.0, 1.0)
        counters = wait_processed(client, 2)
        assert counters.get("isms_fused") == 1
        assert client.stats().rejected == {"robot_mismatch": 1}
        wait_until(lambda: "robotA" in {e.robot for e in client.robots().robots}, 10.0)
        assert {e.robot for e in client.robots().robots} == {"robotA"}
        assert client.stats().counters.get("poses_rejected_robot_mismatch") == 1


def test_serve_without_endpoints_listens_where_clients_connect_by_default(tmp_path: Path) -> None:
    """``sogm-service serve`` with no endpoint listens on tcp/127.0.0.1:7447, the default of
    every client command, and says so."""
    import socket
    import subprocess
    import sys

    with socket.socket() as s:
        if s.connect_ex(("127.0.0.1", 7447)) == 0:
            pytest.skip("something else listens on 127.0.0.1:7447")
    proc = subprocess.Popen([sys.executable, "-m", "sogm_service", "serve"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert proc.stdout is not None
        line = ""
        while "sogm-service: serving map" not in line:
            line = proc.stdout.readline()
            assert line, "serve exited"
        assert "tcp/127.0.0.1:7447" in line
        with MapClient.connect(timeout=10.0) as client:  # the client's default endpoint
            assert client.info().map == "default"
    finally:
        proc.terminate()
        assert proc.wait(15) == 0


def test_prob_u8_v2_over_the_wire(server: ServerProcess) -> None:
    """Codes 0 / 127 / 254 / 255 in four bands, published as raw msgpack to a real server."""
    data = np.zeros((40, 40), np.uint8)
    data[:, 10:20], data[:, 20:30], data[:, 30:] = 127, 254, 255
    nan_ism = np.full((40, 40), np.nan, np.float32)
    with server.client() as client:
        client.publish_raw("ism/r/laser/obstacle", ism_payload(data, "prob_u8_v2"))
        client.publish_raw("ism/r/laser/obstacle", ism_payload(nan_ism, "prob_f32"))
        counters = wait_processed(client, 2)
        assert counters.get("isms_fused") == 2, counters
        window = dict(x=1.0, y=1.0, width=2.0, height=2.0, resolution=0.05, interp="nearest")
        l = client.submap(**window, encoding="logodds_i16").data[0]
        v2 = client.submap(**window, encoding="prob_u8_v2").data[0]
    assert (l[:, :10] == LO).all() and (l[:, 10:20] == 0).all()
    assert (l[:, 20:30] == HI).all() and (l[:, 30:] == 0).all()
    assert (v2[:, :10] == 0).all() and (v2[:, 10:20] == 255).all()
    assert (v2[:, 20:30] == 254).all() and (v2[:, 30:] == 255).all()
