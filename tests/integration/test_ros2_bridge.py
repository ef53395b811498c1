"""The ROS 2 bridge against a ROS 2 side built from rmw_zenoh's wire as documented by the
rmw_zenoh project, over real Zenoh sessions.

The "ROS" side here follows that documentation by hand: keys and token keys are
literal strings, CDR comes from rosbags, attachments are ``struct.pack`` + xxhash.  Nothing on
that side uses the project's own encoders.
"""

from __future__ import annotations

import math
import re
import struct
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

pytest.importorskip("rosbags")  # the [ros2] extra
xxhash = pytest.importorskip("xxhash")

import zenoh  # noqa: E402
import zenoh.ext  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402
from rosbags.typesys.base import Nodetype  # noqa: E402

from sogm_service.adapters.ros2.convert import window_to_grid  # noqa: E402
from sogm_service.adapters.ros2.extent import publish_region  # noqa: E402
from sogm_service.adapters.ros2.views import MapSnapshot, map_snapshot  # noqa: E402
from sogm_service.client import MapClient  # noqa: E402
from sogm_service.client.session import free_tcp_endpoint, loopback_settings, open_session  # noqa: E402
from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice  # noqa: E402
from sogm_service.core.map.tiles import TiledMap  # noqa: E402
from sogm_service.service.ros2.bridge import Ros2Bridge  # noqa: E402
from sogm_service.service.ros2.settings import Ros2BridgeSettings  # noqa: E402
from sogm_service.service.server import pipeline  # noqa: E402
from sogm_service.wire import codec  # noqa: E402
from sogm_service.wire.messages import IsmMessage, PoseModel  # noqa: E402
from tests.conftest import wait_until  # noqa: E402

pytestmark = pytest.mark.integration

GRID_T = "nav_msgs::msg::dds_::OccupancyGrid_"
GRID_H = "RIHS01_8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7"
POSE_T = "geometry_msgs::msg::dds_::PoseStamped_"
POSE_H = "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8"
TF_T = "tf2_msgs::msg::dds_::TFMessage_"
TF_H = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"
GETMAP_T = "nav_msgs::srv::dds_::GetMap_"
GETMAP_H = "RIHS01_c8ae77c9995b3554b5ba80e4d4d443f970ac65143102a1d893ec24fc07b31147"
MAP = "testmap"
TIMEOUT = 5.0

TS = get_typestore(Stores.ROS2_JAZZY)
TS.register({
    "nav_msgs/srv/GetMap_Request": ([], [("structure_needs_at_least_one_member",
                                          (Nodetype.BASE, ("uint8", 0)))]),
    "nav_msgs/srv/GetMap_Response": ([], [("map", (Nodetype.NAME,
                                                   "nav_msgs/msg/OccupancyGrid"))]),
})
T = TS.types


def spec_gid(token_key: str) -> bytes:
    v = xxhash.xxh3_128_intdigest(token_key.encode())
    return struct.pack("<QQ", v & (2**64 - 1), v >> 64)


def spec_attachment(seq: int, gid: bytes) -> bytes:
    return struct.pack("<qq", seq, time.time_ns()) + bytes([16]) + gid


class SpecPublisher:
    """A ROS 2 publisher as rmw_zenoh puts one on Zenoh (advanced publisher, token, gid)."""

    def __init__(self, session: zenoh.Session, topic: str, dds_type: str, type_hash: str,
                 entity_id: int, qos: str = "::,10:,:,:,,") -> None:
        zid = str(session.info.zid())
        self.key = f"0/{topic.strip('/')}/{dds_type}/{type_hash}"
        self.token_key = (f"@ros2_lv/0/{zid}/0/{entity_id}/MP/%/%/spec_robot/"
                          f"{topic.replace('/', '%')}/{dds_type}/{type_hash}/{qos}")
        self.gid = spec_gid(self.token_key)
        self.token = session.liveliness().declare_token(self.token_key)
        self.pub = zenoh.ext.declare_advanced_publisher(session, self.key)
        self.seq = 0

    def put(self, payload: bytes, attachment: bytes | str | None = "spec") -> None:
        self.seq += 1
        if attachment == "spec":
            self.pub.put(payload, attachment=spec_attachment(self.seq, self.gid))
        elif attachment is None:
            self.pub.put(payload)
        else:
            self.pub.put(payload, attachment=attachment)

    def close(self) -> None:
        self.pub.undeclare()
        self.token.undeclare()


def header(frame: str, sec: int, nanosec: int = 0) -> Any:
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
        sec=sec, nanosec=nanosec), frame_id=frame)


def quat(yaw: float, tilt: float = 0.0) -> Any:
    if tilt:
        return T["geometry_msgs/msg/Quaternion"](x=math.sin(tilt / 2), y=0.0, z=0.0,
                                                 w=math.cos(tilt / 2))
    return T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2),
                                             w=math.cos(yaw / 2))


def grid_cdr(cells: np.ndarray, *, res: float, x: float, y: float, yaw: float,
             tilt: float = 0.0) -> bytes:
    h, w = cells.shape
    msg = T["nav_msgs/msg/OccupancyGrid"](
        header=header("map", 20, 250_000_000),
        info=T["nav_msgs/msg/MapMetaData"](
            map_load_time=T["builtin_interfaces/msg/Time"](sec=0, nanosec=0), resolution=res,
            width=w, height=h, origin=T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
                orientation=quat(yaw, tilt))),
        data=cells.astype(np.int8).ravel())
    return bytes(TS.serialize_cdr(msg, "nav_msgs/msg/OccupancyGrid"))


@dataclass
class Recorder:
    isms: list[tuple[str, str, IsmMessage]] = field(default_factory=list)
    poses: list[tuple[str, float, float, float, float]] = field(default_factory=list)
    rejects: list[tuple[str, str]] = field(default_factory=list)
    rejected_what: list[str] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_ism(self, key: str, layer: str, msg: IsmMessage) -> None:
        with self.lock:
            self.isms.append((key, layer, msg))

    def on_pose(self, robot: str, x: float, y: float, yaw: float, stamp: float) -> None:
        with self.lock:
            self.poses.append((robot, x, y, yaw, stamp))

    def on_reject(self, what: str, code: str, text: str) -> None:
        with self.lock:
            self.rejects.append((code, text))
            self.rejected_what.append(what)


@dataclass
class Rig:
    bridge: Ros2Bridge
    ros: zenoh.Session
    rec: Recorder
    snaps: list[MapSnapshot]


def tokens(session: zenoh.Session) -> list[str]:
    return [str(r.ok.key_expr) for r in session.liveliness().get("@ros2_lv/0/**",
                                                                  timeout=TIMEOUT) if r.ok]


def barrier(sender: zenoh.Session, receiver: zenoh.Session) -> None:
    """Wait until what ``sender`` declared so far has reached ``receiver``: a liveliness token
    declared now travels after those declarations on the same link."""
    key = f"sogm_test/barrier/{time.monotonic_ns()}"
    token = sender.liveliness().declare_token(key)
    try:
        assert wait_until(lambda: any(r.ok for r in receiver.liveliness().get(
            key, timeout=TIMEOUT)), TIMEOUT)
    finally:
        token.undeclare()


@pytest.fixture
def rig() -> Iterator[Rig]:
    endpoint = free_tcp_endpoint()
    server_side = open_session(loopback_settings(listen=endpoint))
    ros = open_session(loopback_settings(connect=endpoint))
    rec = Recorder()
    snaps: list[MapSnapshot] = []
    bridge = Ros2Bridge(server_side, map_name=MAP,
                        settings=Ros2BridgeSettings(humble=True),
                        on_ism=rec.on_ism, on_pose=rec.on_pose, on_reject=rec.on_reject,
                        map_source=lambda: snaps[-1] if snaps else MapSnapshot())
    try:
        # The bridge's service token is declared after its subscriptions: once the ROS side
        # sees it, those declarations have reached it too.
        zid = str(server_side.info.zid())
        ss = (f"@ros2_lv/0/{zid}/0/" + r"\d+" + f"/SS/%/%/sogm_service/%sogm%{MAP}%get_map/"
              f"{GETMAP_T}/{GETMAP_H}/::,10:,:,:,,")
        assert wait_until(lambda: any(re.fullmatch(ss, t) for t in tokens(ros)), TIMEOUT)
        yield Rig(bridge, ros, rec, snaps)
    finally:
        bridge.close()
        ros.close()
        server_side.close()


def test_tokens_are_the_spec_formats(rig: Rig) -> None:
    zid = rig.bridge.zid
    found = tokens(rig.ros)
    assert f"@ros2_lv/0/{zid}/0/0/NN/%/%/sogm_service" in found
    tf = f"/MS/%/%/sogm_service/%tf/{TF_T}/{TF_H}/::,100:,:,:,,"
    assert any(t.startswith(f"@ros2_lv/0/{zid}/0/") and t.endswith(tf) for t in found)
    # a ROS publisher appears: the bridge declares its subscription to that topic
    pub = SpecPublisher(rig.ros, "/ism/robot9/floor", GRID_T, GRID_H, entity_id=31)
    try:
        ms = re.compile(f"@ros2_lv/0/{zid}/0/" + r"\d+" + "/MS/%/%/sogm_service/"
                        f"%ism%robot9%floor/{GRID_T}/{GRID_H}/" + re.escape("::,10:,:,:,,"))
        assert wait_until(lambda: any(ms.fullmatch(t) for t in tokens(rig.ros)), TIMEOUT)
    finally:
        pub.close()


def test_spec_grid_reaches_on_ism_and_fuses_like_the_native_ism(rig: Rig) -> None:
    rng = np.random.default_rng(7)
    cells = rng.choice(np.array([-1, 0, 10, 50, 90, 100], np.int8), size=(30, 40))
    yaw = 0.3
    pub = SpecPublisher(rig.ros, "/ism/robot1/obstacle", GRID_T, GRID_H, entity_id=11)
    try:
        pub.put(grid_cdr(cells, res=0.05, x=1.0, y=-0.5, yaw=yaw))
        assert wait_until(lambda: len(rig.rec.isms) == 1, TIMEOUT), rig.rec.rejects
    finally:
        pub.close()
    key, layer, msg = rig.rec.isms[0]
    assert key == f"0/ism/robot1/obstacle/{GRID_T}/{GRID_H}"
    assert (layer, msg.layer, msg.robot) == ("robot1/obstacle", "robot1/obstacle", "robot1")
    assert msg.resolution == 0.05 and (msg.width, msg.height) == (40, 30)
    assert (msg.origin.x, msg.origin.y) == (1.0, -0.5)
    assert msg.origin.yaw == pytest.approx(yaw, abs=1e-12)
    assert msg.stamp == pytest.approx(20.25) and msg.frame == "map"
    assert np.array_equal(msg.array(), cells)
    # The same ISM as a native robot sends it (msgpack through the wire codec), fused alike.
    native = codec.decode(IsmMessage, codec.encode(IsmMessage(
        frame="map", stamp=20.25, robot="robot1", resolution=0.05,
        origin=PoseModel(x=1.0, y=-0.5, yaw=msg.origin.yaw), width=40, height=30,
        encoding="occupancy_i8", data=cells.tobytes())))
    maps = []
    for m in (msg, native):
        tiled = TiledMap(MAP, "map", TileLattice(0.05, 256))
        pipeline.fuse_ism(tiled, m, "robot1/obstacle")
        maps.append(tiled)
    window = GridGeometry(0.05, 80, 80, Pose2D(-1.0, -2.5, 0.0))
    a = maps[0].sample(window, ["robot1/obstacle"], "nearest")
    b = maps[1].sample(window, ["robot1/obstacle"], "nearest")
    assert np.count_nonzero(a) > 500 and np.array_equal(a, b)


def test_bad_samples_are_refused_with_their_codes(rig: Rig) -> None:
    good = grid_cdr(np.zeros((2, 3), np.int8), res=0.05, x=0.0, y=0.0, yaw=0.0)
    pub = SpecPublisher(rig.ros, "/ism/robot2/obstacle", GRID_T, GRID_H, entity_id=12)
    try:
        pub.put(good, attachment=None)  # no attachment
        pub.put(good, attachment=b"\x01\x02\x03")  # not an attachment
        pub.put(good[:-4])  # truncated CDR
        pub.put(grid_cdr(np.zeros((2, 3), np.int8), res=0.05, x=0.0, y=0.0, yaw=0.0,
                         tilt=0.3))  # not a rotation about z
        pub.put(grid_cdr(np.full((2, 3), 120, np.int8), res=0.05, x=0.0, y=0.0, yaw=0.0))
        gid = pub.gid  # the older keyed attachment form is still accepted
        keyed = zenoh.ext.z_serialize(("sequence_number", zenoh.ext.Int64(9),
                                       "source_timestamp", zenoh.ext.Int64(time.time_ns()),
                                       "source_gid", gid)).to_bytes()
        pub.put(good, attachment=keyed)
        assert wait_until(lambda: len(rig.rec.rejects) == 5 and len(rig.rec.isms) == 1,
                          TIMEOUT), (rig.rec.rejects, rig.rec.isms)
    finally:
        pub.close()
    codes = [c for c, _ in rig.rec.rejects]
    assert set(rig.rec.rejected_what) == {"ism"}
    assert codes == ["bad_attachment", "bad_attachment", "bad_cdr", "non_planar",
                     "out_of_range"]
    assert rig.bridge.stats()["rejected"] == {"bad_attachment": 2, "bad_cdr": 1,
                                              "non_planar": 1, "out_of_range": 1}


def test_humble_samples_and_unknown_hashes(rig: Rig) -> None:
    good = grid_cdr(np.zeros((2, 2), np.int8), res=0.1, x=0.0, y=0.0, yaw=0.0)
    humble = SpecPublisher(rig.ros, "/ism/old/floor", GRID_T, "TypeHashNotSupported", 13)
    other = SpecPublisher(rig.ros, "/ism/new/floor", GRID_T, "RIHS01_" + "ab" * 32, 14)
    try:
        humble.put(good)
        other.put(good)
        assert wait_until(lambda: len(rig.rec.isms) == 1 and len(rig.rec.rejects) == 1,
                          TIMEOUT)
    finally:
        humble.close()
        other.close()
    assert rig.rec.isms[0][1] == "old/floor"
    assert rig.rec.rejects[0][0] == "type_hash"


def test_poses_from_pose_stamped_and_tf(rig: Rig) -> None:
    pose_pub = SpecPublisher(rig.ros, "/robot1/pose", POSE_T, POSE_H, entity_id=15)
    tf_pub = SpecPublisher(rig.ros, "/tf", TF_T, TF_H, entity_id=16, qos="::,100:,:,:,,")
    try:
        msg = T["geometry_msgs/msg/PoseStamped"](header=header("map", 5), pose=T[
            "geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=3.0, y=4.0, z=0.0),
                                      orientation=quat(0.5)))
        pose_pub.put(bytes(TS.serialize_cdr(msg, "geometry_msgs/msg/PoseStamped")))
        odom_frame = T["geometry_msgs/msg/PoseStamped"](header=header("odom", 5), pose=msg.pose)
        pose_pub.put(bytes(TS.serialize_cdr(odom_frame, "geometry_msgs/msg/PoseStamped")))

        def tfs(parent: str, child: str, x: float, yaw: float) -> Any:
            return T["geometry_msgs/msg/TransformStamped"](
                header=header(parent, 6), child_frame_id=child,
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=x, y=0.0, z=0.0),
                    rotation=quat(yaw)))
        tf = T["tf2_msgs/msg/TFMessage"](transforms=[
            tfs("map", "robot2/odom", 2.0, math.pi / 2), tfs("robot2/odom", "robot2/base_link",
                                                            1.0, 0.0)])
        tf_pub.put(bytes(TS.serialize_cdr(tf, "tf2_msgs/msg/TFMessage")))
        assert wait_until(lambda: len(rig.rec.poses) == 2 and len(rig.rec.rejects) == 1,
                          TIMEOUT), rig.rec.rejects
    finally:
        pose_pub.close()
        tf_pub.close()
    assert (rig.rec.rejected_what, rig.rec.rejects[0][0]) == (["pose"], "wrong_frame")
    by_robot = {p[0]: p for p in rig.rec.poses}
    r1 = by_robot["robot1"]
    assert r1[1:3] == (3.0, 4.0) and r1[3] == pytest.approx(0.5) and r1[4] == 5.0
    r2 = by_robot["robot2"]
    assert r2[1] == pytest.approx(2.0) and r2[2] == pytest.approx(1.0)
    assert r2[3] == pytest.approx(math.pi / 2) and r2[4] == 6.0


def _decode_grid(payload: bytes) -> Any:
    return TS.deserialize_cdr(payload, "nav_msgs/msg/OccupancyGrid")


def _expected_cells(fixed: np.ndarray) -> np.ndarray:
    """nav_msgs cells of fixed log-odds (1/1000 nat), by hand: -1 where 0 (never observed)."""
    p = 1.0 / (1.0 + np.exp(-fixed.astype(np.float64) / 1000.0))
    out = np.rint(p * 100).astype(np.int8)
    out[fixed == 0] = -1
    return out


def test_layers_and_map_reach_a_ros_subscriber_and_a_late_one(rig: Rig) -> None:
    # a map with two layers; the bridge publishes the region around a robot, as the server
    tiled = TiledMap(MAP, "map", TileLattice(0.05, 256))
    rng = np.random.default_rng(3)
    for name, x0 in (("robot1/obstacle", 0.5), ("robot1/person", 0.8)):
        cells = rng.choice(np.array([-1, 0, 20, 80, 100], np.int8), size=(20, 20))
        pipeline.fuse_ism(tiled, IsmMessage(resolution=0.05, width=20, height=20,
                                            encoding="occupancy_i8", data=cells.tobytes(),
                                            origin=PoseModel(x=x0, y=0.5)), name)
    window = publish_region(tiled, [(1.0, 1.0)], mode="robots", radius_m=0.75)
    assert window == GridGeometry(0.05, 30, 30, Pose2D(0.25, 0.25, 0.0))
    rig.snaps.append(map_snapshot(tiled, window, stamp=9.5, method="max"))
    stack = tiled.sample(window, ["robot1/obstacle", "robot1/person"], "nearest")
    expect_layer = _expected_cells(stack[0])
    # P_M by hand: the max over the layers that observed a cell (not 0), unknown if none did
    pooled = np.where(stack == 0, np.int16(-32768), stack).max(axis=0)
    expect_map = _expected_cells(np.where(pooled == -32768, 0, pooled))
    assert not np.array_equal(expect_layer, expect_map)

    got: list[tuple[str, bytes, bytes]] = []
    sub = rig.ros.declare_subscriber(
        f"0/sogm/{MAP}/**", lambda s: got.append((str(s.key_expr), s.payload.to_bytes(),
                                                   s.attachment.to_bytes()
                                                   if s.attachment else b"")))
    try:
        barrier(rig.ros, rig.bridge.session)  # the subscription has reached the bridge
        assert rig.bridge.publish_maps() == 3
        assert wait_until(lambda: len(got) >= 3, TIMEOUT)
    finally:
        sub.undeclare()
    expected = {f"0/sogm/{MAP}/layers/robot1/obstacle/{GRID_T}/{GRID_H}": expect_layer,
                f"0/sogm/{MAP}/layers/robot1/person/{GRID_T}/{GRID_H}": _expected_cells(stack[1]),
                f"0/sogm/{MAP}/map/{GRID_T}/{GRID_H}": expect_map}
    assert {k for k, _, _ in got} == set(expected) and len(got) == 3
    assert np.count_nonzero(expect_layer >= 0) > 100
    found = tokens(rig.ros)
    for key, payload, att in got:
        m = _decode_grid(payload)
        assert (m.info.width, m.info.height) == (30, 30) and m.header.frame_id == "map"
        assert m.info.resolution == pytest.approx(0.05) and m.header.stamp.sec == 9
        assert (m.info.origin.position.x, m.info.origin.position.y) == (0.25, 0.25)
        assert np.array_equal(np.asarray(m.data).reshape(30, 30), expected[key])
        assert len(att) == 33 and att[16] == 16
        seq, stamp_ns = struct.unpack_from("<qq", att)
        assert seq == 1 and abs(stamp_ns - time.time_ns()) < 600e9
        topic = key.split(f"/{GRID_T}/")[0].split("/", 1)[1]  # without the domain
        mp = [t for t in found if f"/MP/%/%/sogm_service/%{topic.replace('/', '%')}/" in t]
        assert len(mp) == 1 and mp[0].endswith(f"/{GRID_T}/{GRID_H}/:1:,1:,:,:,,")
        assert att[17:] == spec_gid(mp[0])  # gid = XXH3-128 of the publisher's token
    # unchanged maps are not sent again
    assert rig.bridge.publish_maps() == 0
    # a late joiner (history + late publisher detection, as rmw_zenoh's transient local)
    late: list[tuple[str, bytes, bytes]] = []
    adv = zenoh.ext.declare_advanced_subscriber(
        rig.ros, f"0/sogm/{MAP}/map/{GRID_T}/*",
        lambda s: late.append((str(s.key_expr), s.payload.to_bytes(),
                               s.attachment.to_bytes() if s.attachment else b"")),
        history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=1))
    try:
        assert wait_until(lambda: len(late) >= 1, TIMEOUT)
    finally:
        adv.undeclare()
    m = _decode_grid(late[0][1])
    assert np.array_equal(np.asarray(m.data).reshape(30, 30), expect_map)
    assert struct.unpack_from("<q", late[0][2])[0] == 1


def test_get_map_answers_with_the_request_echoed(rig: Rig) -> None:
    grid = window_to_grid(np.array([[0, 3000], [-3000, 0]], np.int16),
                          GridGeometry(0.1, 2, 2, Pose2D(1.0, 2.0, 0.0)), kind="fixed")
    rig.snaps.append(MapSnapshot({}, grid))
    client_token = "@ros2_lv/0/abc/0/40/SC/%/%/nav2_client/%sogm%testmap%get_map/" \
                   f"{GETMAP_T}/{GETMAP_H}/::,10:,:,:,,"
    gid = spec_gid(client_token)
    request = bytes(TS.serialize_cdr(T["nav_msgs/srv/GetMap_Request"](
        structure_needs_at_least_one_member=0), "nav_msgs/srv/GetMap_Request"))
    replies = list(rig.ros.get(f"0/sogm/{MAP}/get_map/{GETMAP_T}/{GETMAP_H}", payload=request,
                               attachment=struct.pack("<qqB", 77, time.time_ns(), 16) + gid,
                               target=zenoh.QueryTarget.ALL_COMPLETE, timeout=TIMEOUT))
    assert len(replies) == 1 and replies[0].ok is not None
    r = replies[0].ok
    att = r.attachment.to_bytes()
    assert len(att) == 33 and struct.unpack_from("<q", att)[0] == 77 and att[17:] == gid
    resp = TS.deserialize_cdr(r.payload.to_bytes(), "nav_msgs/srv/GetMap_Response")
    assert np.asarray(resp.map.data).tolist() == [-1, 95, 5, -1]
    assert (resp.map.info.origin.position.x, resp.map.info.origin.position.y) == (1.0, 2.0)
    # without an attachment: refused, with an error reply
    bad = list(rig.ros.get(f"0/sogm/{MAP}/get_map/{GETMAP_T}/{GETMAP_H}", payload=request,
                           timeout=TIMEOUT))
    assert len(bad) == 1 and bad[0].err is not None
    assert bad[0].err.payload.to_bytes().startswith(b"bad_attachment")


def test_serve_with_ros2_fuses_a_spec_grid_like_a_native_ism_and_publishes_the_map(
        tmp_path: Any) -> None:
    """The real ``serve`` with ``[ros2] enabled``: a grid from a spec-built ROS publisher goes
    through the server's own pipeline (the same cells as the native ISM fused in the core), and
    a ROS subscriber gets the fused map, decoded with rosbags."""
    from tests.conftest import start_server, wait_processed

    srv = start_server(tmp_path, {"map": {"name": MAP},
                                  "ros2": {"enabled": True, "publish_period_s": 0.2,
                                           "region": "known"}})
    ros = open_session(loopback_settings(connect=srv.endpoint))
    maps: list[bytes] = []
    sub = ros.declare_subscriber(f"0/sogm/{MAP}/map/{GRID_T}/*",
                                 lambda s: maps.append(s.payload.to_bytes()))
    pub = SpecPublisher(ros, "/ism/robot1/obstacle", GRID_T, GRID_H, entity_id=21)
    try:
        zid_ss = "/SS/%/%/sogm_service/"  # the server's GetMap token: declared last
        assert wait_until(lambda: any(zid_ss in t for t in tokens(ros)), TIMEOUT)
        cells = np.random.default_rng(5).choice(np.array([-1, 0, 30, 70, 100], np.int8),
                                                size=(40, 50))
        pub.put(grid_cdr(cells, res=0.05, x=0.5, y=0.25, yaw=0.0))
        with MapClient.connect(srv.endpoint, map_name=MAP) as client:
            counters = wait_processed(client, 1)
            assert counters.get("isms_fused") == 1, client.stats().rejected
            window = dict(x=1.75, y=1.25, width=2.5, height=2.0, resolution=0.05,
                          encoding="logodds_i16")
            got = client.submap(**window)
        local = TiledMap(MAP, "map", TileLattice(0.05, 256))
        pipeline.fuse_ism(local, IsmMessage(
            robot="robot1", stamp=20.25, resolution=0.05, origin=PoseModel(x=0.5, y=0.25),
            width=50, height=40, encoding="occupancy_i8", data=cells.tobytes()),
            "robot1/obstacle")
        assert got.layers == ["robot1/obstacle"]
        want = local.sample(got.geometry, ["robot1/obstacle"], "biodds")
        assert np.count_nonzero(want) > 1000 and np.array_equal(got.data, want)
        assert wait_until(lambda: bool(maps), TIMEOUT)
        grid = _decode_grid(maps[-1])
        assert grid.info.resolution == pytest.approx(0.05) and grid.header.frame_id == "map"
        assert (np.asarray(grid.data) != -1).sum() >= np.count_nonzero(cells != -1)
    finally:
        pub.close()
        sub.undeclare()
        ros.close()
        assert srv.terminate() == 0
