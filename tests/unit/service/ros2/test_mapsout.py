"""When the bridge sends a whole OccupancyGrid and when only OccupancyGridUpdates
(service/ros2/mapsout), over real Zenoh sessions on 127.0.0.1; what the subscriber receives is
read with rosbags from the message definitions."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

pytest.importorskip("rosbags")  # the [ros2] extra
pytest.importorskip("xxhash")

from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from sogm_service.adapters.ros2.cdr import OccupancyGridFields
from sogm_service.client.session import free_tcp_endpoint, loopback_settings, open_session
from sogm_service.service.ros2.bridge import Ros2Bridge
from sogm_service.service.ros2.settings import Ros2BridgeSettings
from tests.conftest import wait_until

UPDATE = "map_msgs/msg/OccupancyGridUpdate"
TS = get_typestore(Stores.ROS2_JAZZY)
TS.register(get_types_from_msg(
    "std_msgs/Header header\nint32 x\nint32 y\nuint32 width\nuint32 height\nint8[] data\n",
    UPDATE))
TIMEOUT = 5.0


class Got:
    def __init__(self) -> None:
        self.samples: list[tuple[str, Any]] = []
        self.lock = threading.Lock()

    def __call__(self, sample: Any) -> None:
        key, raw = str(sample.key_expr), sample.payload.to_bytes()
        kind = "update" if "OccupancyGridUpdate_" in key else "grid"
        msg = TS.deserialize_cdr(raw, UPDATE if kind == "update" else
                                 "nav_msgs/msg/OccupancyGrid")
        with self.lock:
            self.samples.append((kind, msg))

    def take(self, n: int) -> list[tuple[str, Any]]:
        assert wait_until(lambda: len(self.samples) >= n, TIMEOUT), self.samples
        with self.lock:
            out, self.samples = self.samples, []
        assert len(out) == n, [k for k, _ in out]
        return out


@pytest.fixture
def rig(request: pytest.FixtureRequest) -> Iterator[tuple[Ros2Bridge, Got]]:
    endpoint = free_tcp_endpoint()
    server_side = open_session(loopback_settings(listen=endpoint))
    ros = open_session(loopback_settings(connect=endpoint))
    got = Got()
    bridge = Ros2Bridge(server_side, map_name="m",
                        settings=Ros2BridgeSettings(full_period_s=request.param))
    sub = ros.declare_subscriber("0/sogm/m/**", got)
    try:
        assert wait_until(lambda: any(True for r in server_side.liveliness().get(
            "@ros2_lv/0/**", timeout=TIMEOUT) if r.ok), TIMEOUT)
        token = ros.liveliness().declare_token("sogm_test/ready")  # after the subscription
        assert wait_until(lambda: any(r.ok for r in server_side.liveliness().get(
            "sogm_test/ready", timeout=TIMEOUT)), TIMEOUT)
        token.undeclare()
        yield bridge, got
    finally:
        sub.undeclare()
        bridge.close()
        ros.close()
        server_side.close()


def grid(data: np.ndarray, x: float = 0.0) -> OccupancyGridFields:
    h, w = data.shape
    return OccupancyGridFields("map", 5.0, 0.05, w, h, (x, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0),
                               data.copy())


@pytest.mark.parametrize("rig", [0.0], indirect=True)
def test_first_whole_then_updates_then_whole_on_a_new_extent(
        rig: tuple[Ros2Bridge, Got]) -> None:
    bridge, got = rig
    cells = np.full((128, 128), -1, np.int8)
    assert bridge.publish_grid(bridge.map_topic, grid(cells))
    [(kind, m)] = got.take(1)
    assert kind == "grid" and (m.info.width, m.info.height) == (128, 128)
    assert not bridge.publish_grid(bridge.map_topic, grid(cells))  # unchanged: nothing
    cells[3:5, 70:73] = 90
    assert bridge.publish_grid(bridge.map_topic, grid(cells))
    [(kind, u)] = got.take(1)
    assert kind == "update" and (u.x, u.y, u.width, u.height) == (70, 3, 3, 2)
    assert np.asarray(u.data).tolist() == [90] * 6
    # the updates' publisher token: rmw_zenoh's format, map_msgs' hash, the map topics' QoS
    tokens = [t for t in bridge.token_keys() if "/MP/" in t and "map_updates" in t]
    assert len(tokens) == 1 and tokens[0].endswith(
        "/MP/%/%/sogm_service/%sogm%m%map_updates/map_msgs::msg::dds_::OccupancyGridUpdate_/"
        "RIHS01_c4095b0be2e4363f8978a1570e0293ee093436f1e1c61d99b48502ac317025e8/:1:,1:,:,:,,")
    # the same cells on a moved extent: a whole grid, and the latched update replaced by an
    # empty one (a late subscriber never writes an older update into a newer grid)
    assert bridge.publish_grid(bridge.map_topic, grid(cells, x=3.2))
    (kind, m), (kind2, u) = got.take(2)
    assert kind == "grid" and m.info.origin.position.x == pytest.approx(3.2)
    assert kind2 == "update" and (u.width, u.height) == (0, 0)
    # more than half the grid changed: the whole grid, not updates
    cells[:100] = 50
    assert bridge.publish_grid(bridge.map_topic, grid(cells, x=3.2))
    [(kind, m)] = got.take(1)
    assert kind == "grid" and np.asarray(m.data)[0] == 50
    c = bridge.stats()["counters"]
    assert c["grids_published"] == 3 and c["updates_published"] == 2
    assert c["updates_published_bytes"] < c["grids_published_bytes"] / 100


@pytest.mark.parametrize("rig", [0.3], indirect=True)
def test_a_whole_grid_again_full_period_s_after_updates(rig: tuple[Ros2Bridge, Got]) -> None:
    bridge, got = rig
    cells = np.zeros((64, 64), np.int8)
    bridge.publish_grid(bridge.map_topic, grid(cells))
    got.take(1)
    cells[0, 0] = 1
    bridge.publish_grid(bridge.map_topic, grid(cells))
    assert [k for k, _ in got.take(1)] == ["update"]
    assert wait_until(lambda: bridge.publish_grid(bridge.map_topic, grid(cells)), TIMEOUT)
    out = got.take(2)  # nothing changed, but updates followed the last whole grid
    assert [k for k, _ in out] == ["grid", "update"]
    assert np.asarray(out[0][1].data)[0] == 1 and out[1][1].width == 0
    assert not bridge.publish_grid(bridge.map_topic, grid(cells))  # the latched pair is current


@pytest.mark.parametrize("rig", [0.0], indirect=True)
def test_a_subscriber_that_joins_after_updates_gets_a_whole_grid(
        rig: tuple[Ros2Bridge, Got]) -> None:
    bridge, got = rig
    cells = np.zeros((64, 64), np.int8)
    bridge.publish_grid(bridge.map_topic, grid(cells))
    got.take(1)
    assert not bridge.publish_grid(bridge.map_topic, grid(cells))  # current: nothing
    cells[0, 0] = 1
    bridge.publish_grid(bridge.map_topic, grid(cells))
    assert [k for k, _ in got.take(1)] == ["update"]
    assert not bridge.publish_grid(bridge.map_topic, grid(cells))
    # a ROS subscriber appears: its rmw_zenoh liveliness token, by hand from the wire format
    # (the bridge reads the zid from the key: this one is not the bridge's own)
    token = bridge.session.liveliness().declare_token(
        "@ros2_lv/0/aabbccdd/0/11/MS/%/%/rviz/%sogm%m%map/nav_msgs::msg::dds_::"
        "OccupancyGrid_/RIHS01_0000/:1:,1:,:,:,,")
    try:
        assert wait_until(lambda: bridge.stats()["counters"].get("subscribers_joined") == 1,
                          TIMEOUT)
        # its next publication is the whole grid (and the empty update), though nothing changed
        assert bridge.publish_grid(bridge.map_topic, grid(cells))
        out = got.take(2)
        assert [k for k, _ in out] == ["grid", "update"] and np.asarray(out[0][1].data)[0] == 1
        assert not bridge.publish_grid(bridge.map_topic, grid(cells))  # then nothing again
    finally:
        token.undeclare()
