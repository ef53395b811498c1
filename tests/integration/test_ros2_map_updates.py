"""A ROS 2 subscriber of ``/sogm/<map>/map`` and ``/sogm/<map>/map_updates`` that writes every
``map_msgs/msg/OccupancyGridUpdate`` into its last whole grid holds the map the server answers,
against the real ``serve`` with ``[ros2] enabled``; and once the extent is settled the updates
cost a small share of the bytes that republishing whole grids would.

The ROS side is built from the message definitions with rosbags (map_msgs from its definition
text, the hash computed by rosbags) and from rmw_zenoh's wire as documented, as in
``test_ros2_bridge.py``; nothing on that side uses the project's own encoders.
"""

from __future__ import annotations

import struct
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

pytest.importorskip("rosbags")  # the [ros2] extra
pytest.importorskip("xxhash")

from rosbags.typesys import get_types_from_msg

from sogm_service.client import MapClient
from sogm_service.client.session import loopback_settings, open_session
from tests.conftest import start_server, wait_processed, wait_until
from tests.integration.test_ros2_bridge import (
    GETMAP_H,
    GETMAP_T,
    GRID_H,
    GRID_T,
    TS,
    SpecPublisher,
    grid_cdr,
    spec_gid,
    tokens,
)

pytestmark = pytest.mark.integration

MAP = "updmap"
TIMEOUT = 10.0
UPDATE = "map_msgs/msg/OccupancyGridUpdate"
UPDATE_T = "map_msgs::msg::dds_::OccupancyGridUpdate_"
# What `ros2 topic info -v` prints for map_msgs/msg/OccupancyGridUpdate on Jazzy.
UPDATE_H_ROS = "RIHS01_c4095b0be2e4363f8978a1570e0293ee093436f1e1c61d99b48502ac317025e8"

if UPDATE not in TS.types:
    TS.register(get_types_from_msg(
        "std_msgs/Header header\nint32 x\nint32 y\nuint32 width\nuint32 height\nint8[] data\n",
        UPDATE))
UPDATE_H = TS.hash_rihs01(UPDATE)


@dataclass
class Holder:
    """What a ROS subscriber of one map topic and its ``_updates`` holds, and what it got."""

    grid: Any = None  # the last whole grid's message
    data: np.ndarray | None = None  # its cells with every later update written in
    fulls: list[tuple[float, int]] = field(default_factory=list)  # (time, bytes)
    updates: list[tuple[float, int, float]] = field(default_factory=list)  # (time, bytes, stamp)
    misplaced: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_grid(self, sample: Any) -> None:
        raw = sample.payload.to_bytes()
        m: Any = TS.deserialize_cdr(raw, "nav_msgs/msg/OccupancyGrid")
        with self.lock:
            self.grid = m
            self.data = np.array(m.data, dtype=np.int8).reshape(m.info.height, m.info.width)
            self.fulls.append((time.monotonic(), len(raw)))

    def on_update(self, sample: Any) -> None:
        raw = sample.payload.to_bytes()
        u: Any = TS.deserialize_cdr(raw, UPDATE)
        with self.lock:
            stamp = u.header.stamp.sec + u.header.stamp.nanosec * 1e-9
            self.updates.append((time.monotonic(), len(raw), stamp))
            if self.data is None:
                self.misplaced += 1
                return
            h, w = self.data.shape
            if u.x < 0 or u.y < 0 or u.x + u.width > w or u.y + u.height > h:
                self.misplaced += 1  # nav2's static layer refuses such an update
                return
            self.data[u.y:u.y + u.height, u.x:u.x + u.width] = \
                np.asarray(u.data, np.int8).reshape(u.height, u.width)

    def cells(self) -> np.ndarray | None:
        with self.lock:
            return None if self.data is None else self.data.copy()


def get_map(ros: Any) -> Any:
    """The GetMap service, called as a ROS client does (request CDR + attachment)."""
    client_token = "@ros2_lv/0/abc/0/40/SC/%/%/nav2_client/" \
                   f"%sogm%{MAP}%get_map/{GETMAP_T}/{GETMAP_H}/::,10:,:,:,,"
    request = bytes(TS.serialize_cdr(TS.types["nav_msgs/srv/GetMap_Request"](
        structure_needs_at_least_one_member=0), "nav_msgs/srv/GetMap_Request"))
    replies = list(ros.get(f"0/sogm/{MAP}/get_map/{GETMAP_T}/{GETMAP_H}", payload=request,
                           attachment=struct.pack("<qqB", 1, time.time_ns(), 16)
                           + spec_gid(client_token), timeout=TIMEOUT))
    assert len(replies) == 1 and replies[0].ok is not None
    reply: Any = TS.deserialize_cdr(replies[0].ok.payload.to_bytes(),
                                    "nav_msgs/srv/GetMap_Response")
    return reply.map


def expected_cells(fixed: np.ndarray) -> np.ndarray:
    """nav_msgs cells of fixed log-odds (1/1000 nat), by hand: -1 where 0 (never observed)."""
    p = 1.0 / (1.0 + np.exp(-fixed.astype(np.float64) / 1000.0))
    out = np.rint(p * 100).astype(np.int8)
    out[fixed == 0] = -1
    return out


def test_updates_keep_a_ros_subscriber_equal_to_get_map_for_a_share_of_the_bytes(
        tmp_path: Any) -> None:
    assert UPDATE_H == UPDATE_H_ROS  # rosbags' RIHS01 of the definition is ROS 2's
    srv = start_server(tmp_path, {"map": {"name": MAP, "resolution": 0.05, "tile_size": 256},
                                  "ros2": {"enabled": True, "publish_period_s": 0.2,
                                           "region": "known", "full_period_s": 0}})
    ros = open_session(loopback_settings(connect=srv.endpoint))
    fused, layer = Holder(), Holder()
    base = f"0/sogm/{MAP}"
    subs = [ros.declare_subscriber(f"{base}/map/{GRID_T}/{GRID_H}", fused.on_grid),
            ros.declare_subscriber(f"{base}/map_updates/{UPDATE_T}/{UPDATE_H}",
                                   fused.on_update),
            ros.declare_subscriber(f"{base}/layers/robot1/obstacle/{GRID_T}/{GRID_H}",
                                   layer.on_grid),
            ros.declare_subscriber(f"{base}/layers/robot1/obstacle_updates/{UPDATE_T}/{UPDATE_H}",
                                   layer.on_update)]
    pub = SpecPublisher(ros, "/ism/robot1/obstacle", GRID_T, GRID_H, entity_id=31)
    rng = np.random.default_rng(11)
    values = np.array([-1, 0, 30, 70, 100], np.int8)
    sent = 0

    def ism(x: float, y: float, n: int) -> None:
        nonlocal sent
        pub.put(grid_cdr(rng.choice(values, size=(n, n)), res=0.05, x=x, y=y, yaw=0.0))
        sent += 1

    try:
        assert wait_until(lambda: any("/SS/%/%/sogm_service/" in t for t in tokens(ros)),
                          TIMEOUT)
        with MapClient.connect(srv.endpoint, map_name=MAP) as client:
            # two ISMs far apart: the known region (and so the extent) spans several tiles
            ism(1.0, 1.0, 40)
            ism(30.0, 20.0, 40)
            assert wait_processed(client, sent).get("isms_fused") == sent
            assert wait_until(lambda: fused.grid is not None and layer.grid is not None,
                              TIMEOUT)
            time.sleep(0.6)  # the extent's whole grids are out
            info = fused.grid.info
            width, height = info.width, info.height
            assert width >= 768 and height >= 512  # tiles of 12.8 m hold both ISMs
            fulls_before = (len(fused.fulls), len(layer.fulls))
            steady_from = time.monotonic()
            # small ISMs in several places over time, inside the known tiles
            for k, (x, y) in enumerate([(3.0, 2.0), (14.0, 9.0), (25.0, 3.0), (33.0, 22.0),
                                        (8.0, 20.0), (20.0, 12.5), (2.0, 15.0), (28.0, 8.0)]):
                ism(x, y, 30 + 5 * (k % 3))
                wait_processed(client, sent)
                time.sleep(0.35)  # at least one publication between ISMs
            assert client.stats().counters.get("isms_fused") == sent
            # the subscriber's grid becomes the one GetMap answers, and stays it
            want: dict[str, Any] = {}

            def equal() -> bool:
                want["map"] = m = get_map(ros)
                got = fused.cells()
                return got is not None and got.shape == (m.info.height, m.info.width) and \
                    np.array_equal(got, np.asarray(m.data, np.int8).reshape(got.shape))
            assert wait_until(equal, TIMEOUT), "the updated grid never equalled GetMap's"
            m = want["map"]
            g = fused.grid
            assert (g.info.width, g.info.height) == (m.info.width, m.info.height) == (width, height)
            assert (g.info.origin.position.x, g.info.origin.position.y) == \
                (m.info.origin.position.x, m.info.origin.position.y) == (0.0, 0.0)
            # ... which is the server's layer, read natively and converted by hand
            res = 0.05
            native = client.submap(x=width * res / 2, y=height * res / 2, width=width * res,
                                   height=height * res, resolution=res, interp="nearest",
                                   encoding="logodds_i16")
            cells = fused.cells()
            assert cells is not None
            assert np.array_equal(cells, expected_cells(native.data[0]))
            assert np.count_nonzero(cells >= 0) > 8 * 900 * 0.7
            assert wait_until(lambda: np.array_equal(layer.cells(), cells),  # type: ignore[arg-type]
                              TIMEOUT)
    finally:
        pub.close()
        for s in subs:
            s.undeclare()
        ros.close()
        assert srv.terminate() == 0

    # the extent stayed put: no whole grid after it settled, every update inside it
    assert (len(fused.fulls), len(layer.fulls)) == fulls_before
    assert fused.misplaced == 0 and layer.misplaced == 0
    steady = [(n, stamp) for t, n, stamp in fused.updates if t >= steady_from]
    rounds = len({stamp for _, stamp in steady})
    whole = fused.fulls[-1][1]
    update_bytes = sum(n for n, _ in steady)
    assert rounds >= 6, rounds
    share = update_bytes / (rounds * whole)
    print(f"\nsteady state: {rounds} publications with a change, {len(steady)} updates, "
          f"{update_bytes} bytes; whole grids would be {rounds} x {whole} = {rounds * whole} "
          f"bytes ({share:.1%})")
    assert share < 0.20
