"""rmw_zenoh wire formats, checked against the spec (shared/ros2-rmw_zenoh.md) and rosbags.

The expected values here are literal strings from the spec or built by hand from its byte
layout (struct, xxhash, zenoh-ext's own serializer), never with the adapter's encoders.
"""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest

rosbags = pytest.importorskip("rosbags")  # the [ros2] extra
xxhash = pytest.importorskip("xxhash")

import zenoh.ext  # noqa: E402  (the zenoh-ext serializer as an independent reference)
from rosbags.typesys import Stores, get_typestore  # noqa: E402
from rosbags.typesys.base import Nodetype  # noqa: E402

from sogm_service.adapters.ros2 import Ros2DecodeError, cdr, keys  # noqa: E402
from sogm_service.adapters.ros2.attachment import gid_of, parse_attachment  # noqa: E402
from sogm_service.adapters.ros2.convert import (  # noqa: E402
    TfTree,
    grid_to_ism,
    pose_to_robot,
    quaternion_yaw,
    window_to_grid,
)
from sogm_service.core.geometry import GridGeometry, Pose2D  # noqa: E402

SPEC_HASHES = {  # shared/ros2-rmw_zenoh.md, "Known values"
    "nav_msgs/msg/OccupancyGrid":
        "RIHS01_8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7",
    "geometry_msgs/msg/PoseStamped":
        "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8",
    "nav_msgs/msg/Odometry":
        "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
    "tf2_msgs/msg/TFMessage":
        "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
}
# rmw_zenoh's docs/design.md: the add_two_ints service key (a service hash of known value).
ADD_TWO_INTS_HASH = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"

TS = get_typestore(Stores.ROS2_JAZZY)


def _service_hash(srv: str, request: list, response: list) -> str:
    """REP-2011 hash of a service: the description of ``srv`` with request_message,
    response_message and event_message (ServiceEventInfo info, Request[<=1], Response[<=1]).
    ServiceEventInfo's ``char[16] client_gid`` is ``uint8[16]`` in IDL (msg ``char`` = uint8)."""
    ts = get_typestore(Stores.ROS2_JAZZY)
    consts, fields = ts.fielddefs["service_msgs/msg/ServiceEventInfo"]
    fields = [(n, (Nodetype.ARRAY, ((Nodetype.BASE, ("uint8", 0)), 16)))
              if n == "client_gid" else (n, d) for n, d in fields]
    ts.fielddefs["service_msgs/msg/ServiceEventInfo"] = (consts, fields)
    ts.fielddefs[srv + "_Request"] = ([], request)
    ts.fielddefs[srv + "_Response"] = ([], response)
    ts.fielddefs[srv + "_Event"] = ([], [
        ("info", (Nodetype.NAME, "service_msgs/msg/ServiceEventInfo")),
        ("request", (Nodetype.SEQUENCE, ((Nodetype.NAME, srv + "_Request"), 1))),
        ("response", (Nodetype.SEQUENCE, ((Nodetype.NAME, srv + "_Response"), 1)))])
    ts.fielddefs[srv] = ([], [("request_message", (Nodetype.NAME, srv + "_Request")),
                              ("response_message", (Nodetype.NAME, srv + "_Response")),
                              ("event_message", (Nodetype.NAME, srv + "_Event"))])
    return ts.hash_rihs01(srv)


# -- type names, hashes, keys, tokens, QoS ----------------------------------------------------
@pytest.mark.parametrize("ros_type", sorted(SPEC_HASHES))
def test_type_hashes_are_the_spec_literals_and_rosbags_computes_them(ros_type: str) -> None:
    assert keys.TYPE_HASHES[ros_type] == SPEC_HASHES[ros_type]
    assert TS.hash_rihs01(ros_type) == SPEC_HASHES[ros_type]


def test_get_map_hash_by_the_method_that_reproduces_rmw_zenohs_add_two_ints() -> None:
    i64 = (Nodetype.BASE, ("int64", 0))
    assert _service_hash("example_interfaces/srv/AddTwoInts", [("a", i64), ("b", i64)],
                         [("sum", i64)]) == ADD_TWO_INTS_HASH
    get_map = _service_hash("nav_msgs/srv/GetMap", [],
                            [("map", (Nodetype.NAME, "nav_msgs/msg/OccupancyGrid"))])
    assert keys.TYPE_HASHES[keys.GET_MAP] == get_map


def test_data_and_subscription_keys_are_the_spec_examples() -> None:
    assert keys.topic_key(0, "/ism/robot1/obstacle", keys.OCCUPANCY_GRID) == (
        "0/ism/robot1/obstacle/nav_msgs::msg::dds_::OccupancyGrid_/"
        "RIHS01_8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7")
    assert keys.subscription_key(0, "/ism", keys.OCCUPANCY_GRID) == \
        "0/ism/**/nav_msgs::msg::dds_::OccupancyGrid_/*"
    assert keys.pattern_key(3, "/{robot}/pose", keys.POSE_STAMPED) == \
        "3/*/pose/geometry_msgs::msg::dds_::PoseStamped_/*"
    assert keys.service_key(0, "/sogm/m/get_map") == (
        "0/sogm/m/get_map/nav_msgs::srv::dds_::GetMap_/" + keys.TYPE_HASHES[keys.GET_MAP])
    assert keys.dds_type_name("tf2_msgs/msg/TFMessage") == "tf2_msgs::msg::dds_::TFMessage_"
    assert keys.ros_type_name("nav_msgs::srv::dds_::GetMap_") == "nav_msgs/srv/GetMap"


def test_tokens_and_qos_strings_follow_the_spec() -> None:
    assert keys.mangle("/ism/robot1/obstacle") == "%ism%robot1%obstacle"
    assert keys.mangle("/") == "%"
    assert keys.QOS_DEFAULT.key() == "::,10:,:,:,,"  # rclcpp's default, from the spec
    assert keys.QOS_LATCHED.key() == ":1:,1:,:,:,,"  # nav2's /map, from the spec
    assert keys.Qos(reliability=keys.Reliability.BEST_EFFORT, depth=42,
                    deadline=(1, 500)).key() == "2::,:1,500:,:,,"
    assert keys.node_token(0, "abc123", 4, "sogm_service") == \
        "@ros2_lv/0/abc123/4/4/NN/%/%/sogm_service"
    tok = keys.entity_token(0, "abc123", 4, 7, "MP", "sogm_service", "/sogm/m/map",
                            keys.OCCUPANCY_GRID, ":1:,1:,:,:,,")
    assert tok == ("@ros2_lv/0/abc123/4/7/MP/%/%/sogm_service/%sogm%m%map/"
                   "nav_msgs::msg::dds_::OccupancyGrid_/" + SPEC_HASHES[keys.OCCUPANCY_GRID]
                   + "/:1:,1:,:,:,,")
    parsed = keys.parse_token(tok)
    assert (parsed.kind, parsed.topic, parsed.entity_id) == ("MP", "/sogm/m/map", 7)
    with pytest.raises(Ros2DecodeError):
        keys.parse_token("@ros2_lv/0/abc/x")


def test_data_keys_parse_back_to_topic_layer_and_robot() -> None:
    dk = keys.parse_data_key("0/ism/robot1/obstacle/nav_msgs::msg::dds_::OccupancyGrid_/"
                             + SPEC_HASHES[keys.OCCUPANCY_GRID])
    assert (dk.domain, dk.topic, dk.ros_type) == (0, "/ism/robot1/obstacle", keys.OCCUPANCY_GRID)
    keys.check_type(dk, keys.OCCUPANCY_GRID, humble=False)
    assert keys.topic_layer(dk.topic, "/ism") == ("robot1/obstacle", "robot1")
    assert keys.topic_layer("/ism/obstacle", "/ism") == ("obstacle", None)
    humble = keys.parse_data_key("7/ism/r/a/nav_msgs::msg::dds_::OccupancyGrid_/"
                                 "TypeHashNotSupported")
    assert humble.humble and humble.domain == 7
    keys.check_type(humble, keys.OCCUPANCY_GRID, humble=True)
    with pytest.raises(Ros2DecodeError) as e:
        keys.check_type(humble, keys.OCCUPANCY_GRID, humble=False)
    assert e.value.code == "humble_disabled"
    other = keys.parse_data_key("0/ism/r/a/nav_msgs::msg::dds_::OccupancyGrid_/RIHS01_" + "0" * 64)
    with pytest.raises(Ros2DecodeError) as e:
        keys.check_type(other, keys.OCCUPANCY_GRID, humble=True)
    assert e.value.code == "type_hash"
    for bad in ("ism/a", "x/ism/a/nav_msgs::msg::dds_::OccupancyGrid_/TypeHashNotSupported",
                "0/ism/a/OccupancyGrid/TypeHashNotSupported", "0/ism/a/nav_msgs::msg::dds_::X_/h"):
        with pytest.raises(Ros2DecodeError) as e:
            keys.parse_data_key(bad)
        assert e.value.code == "bad_key"
    with pytest.raises(Ros2DecodeError) as e:
        keys.topic_layer("/other/robot1/obstacle", "/ism")
    assert e.value.code == "bad_layer"
    assert keys.robot_from_topic("/{robot}/pose", "/robot7/pose") == "robot7"
    assert keys.robot_from_topic("/{robot}/pose", "/robot7/odom") is None
    assert keys.ros_safe_name("robot1/2d-obstacle.v2") == "robot1/_2d_obstacle_v2"


# -- attachment -----------------------------------------------------------------------------
def _spec_gid(key: str) -> bytes:
    h = xxhash.xxh3_128(key.encode())
    lo, hi = h.intdigest() & (2**64 - 1), h.intdigest() >> 64
    return struct.pack("<QQ", lo, hi)  # "low 64 bits first"


def test_attachment_current_form_built_by_hand_and_by_zenoh_ext() -> None:
    token = "@ros2_lv/0/aa/0/3/MP/%/%/n/%ism%r%a/nav_msgs::msg::dds_::OccupancyGrid_/h/::,10:,:,:,,"
    gid = _spec_gid(token)
    assert gid_of(token) == gid
    by_hand = struct.pack("<qqB", 1, 1_700_000_000_123_456_789, 16) + gid
    assert len(by_hand) == 33
    ts_ns = zenoh.ext.Int64(1_700_000_000_123_456_789)
    by_zenoh = zenoh.ext.z_serialize((zenoh.ext.Int64(1), ts_ns, gid)).to_bytes()
    assert by_zenoh == by_hand
    att = parse_attachment(by_hand)
    assert (att.sequence_number, att.source_timestamp_ns, att.gid) == \
        (1, 1_700_000_000_123_456_789, gid)


def test_attachment_keyed_form_and_humble_gid() -> None:
    gid = bytes(range(16))
    keyed = zenoh.ext.z_serialize(("sequence_number", zenoh.ext.Int64(42), "source_timestamp",
                                   zenoh.ext.Int64(99), "source_gid", gid)).to_bytes()
    assert keyed[0] == 15 and keyed[1:16] == b"sequence_number"
    att = parse_attachment(keyed)
    assert (att.sequence_number, att.source_timestamp_ns, att.gid) == (42, 99, gid)
    humble = struct.pack("<qqB", 3, 4, 24) + bytes(24)
    assert parse_attachment(humble).gid == bytes(24)


@pytest.mark.parametrize("bad", [
    None, b"", b"\x01" * 16, struct.pack("<qqB", 1, 2, 16) + bytes(15),
    struct.pack("<qqB", 1, 2, 16) + bytes(17), struct.pack("<qqB", 1, 2, 8) + bytes(8),
    b"\x0fsequence_number" + bytes(3), struct.pack("<qqB", -1, 2, 16) + bytes(16),
    b"\xff" * 300,
])
def test_bad_attachments_are_refused_with_their_code(bad: bytes | None) -> None:
    with pytest.raises(Ros2DecodeError) as e:
        parse_attachment(bad)
    assert e.value.code == "bad_attachment"
    assert e.value.parameter is None


# -- CDR ------------------------------------------------------------------------------------
def _rosbags_grid(data: np.ndarray, width: int, height: int, *, res: float = 0.05,
                  q: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0),
                  frame: str = "map", x: float = 1.5, y: float = -2.0) -> bytes:
    T = TS.types
    msg = T["nav_msgs/msg/OccupancyGrid"](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
            sec=12, nanosec=500_000_000), frame_id=frame),
        info=T["nav_msgs/msg/MapMetaData"](
            map_load_time=T["builtin_interfaces/msg/Time"](sec=0, nanosec=0), resolution=res,
            width=width, height=height, origin=T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
                orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))),
        data=np.asarray(data, dtype=np.int8))
    return bytes(TS.serialize_cdr(msg, "nav_msgs/msg/OccupancyGrid"))


def test_occupancy_grid_from_rosbags_to_ism() -> None:
    cells = np.array([[0, 100, -1, 50], [25, -1, 0, 100], [1, 2, 3, 4]], dtype=np.int8)
    yaw = 0.4
    raw = _rosbags_grid(cells.ravel(), 4, 3, q=(0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)))
    assert raw[:4] == b"\x00\x01\x00\x00"
    g = cdr.decode_occupancy_grid(raw)
    assert g.resolution == pytest.approx(0.05, abs=1e-8) and g.resolution != 0.05  # float32
    ism = grid_to_ism(g, layer="robot1/obstacle", robot="robot1")
    assert ism.resolution == 0.05  # the float32 read as its shortest decimal
    assert (ism.width, ism.height, ism.encoding, ism.frame) == (4, 3, "occupancy_i8", "map")
    assert (ism.origin.x, ism.origin.y) == (1.5, -2.0)
    assert ism.origin.yaw == pytest.approx(yaw, abs=1e-12)
    assert ism.stamp == pytest.approx(12.5)
    assert np.array_equal(ism.array(), cells)  # row-major, x fastest, row 0 first
    assert (ism.layer, ism.robot) == ("robot1/obstacle", "robot1")


@pytest.mark.parametrize(("mutate", "code"), [
    (lambda raw: raw[:-5], "bad_cdr"),
    (lambda raw: b"", "bad_cdr"),
    (lambda raw: b"\x00\x01\x00\x00" + b"\xff" * 64, "bad_cdr"),
    (lambda raw: b"\x07\x07\x00\x00" + raw[4:], "bad_cdr"),
    (lambda raw: raw[:12] + b"\xff\xff\xff\x7f" + raw[16:], "bad_cdr"),  # frame_id length
    (lambda raw: raw[:-10] + b"\xff\xff\xff\x7f" + raw[-6:], "bad_cdr"),  # data length
])
def test_bad_cdr_is_refused(mutate, code: str) -> None:  # type: ignore[no-untyped-def]
    raw = _rosbags_grid(np.zeros(6), 3, 2)
    with pytest.raises(Ros2DecodeError) as e:
        cdr.decode_occupancy_grid(mutate(raw))
    assert e.value.code == code


def test_grid_content_errors_have_their_codes() -> None:
    with pytest.raises(Ros2DecodeError) as e:  # 6 cells for 3x3
        cdr.decode_occupancy_grid(_rosbags_grid(np.zeros(6), 3, 3))
    assert e.value.code == "data_length"
    with pytest.raises(Ros2DecodeError) as e:
        cdr.decode_occupancy_grid(_rosbags_grid(np.zeros(6), 3, 2), max_cells=5)
    assert e.value.code == "too_large"
    with pytest.raises(Ros2DecodeError) as e:
        cdr.decode_occupancy_grid(_rosbags_grid(np.zeros(6), 3, 2), max_bytes=10)
    assert e.value.code == "too_large"
    with pytest.raises(Ros2DecodeError) as e:  # 101 and -5 are not occupancy values
        grid_to_ism(cdr.decode_occupancy_grid(_rosbags_grid([0, 101, -5, 0, 0, 0], 3, 2)))
    assert e.value.code == "out_of_range"
    with pytest.raises(Ros2DecodeError) as e:
        grid_to_ism(cdr.decode_occupancy_grid(_rosbags_grid(np.zeros(6), 3, 2, res=0.0)))
    assert e.value.code == "non_positive_resolution"
    with pytest.raises(Ros2DecodeError) as e:
        cdr.decode_occupancy_grid(_rosbags_grid(np.zeros(6), 3, 2, x=math.nan))
    assert e.value.code == "non_finite"


def test_non_planar_and_degenerate_quaternions_are_refused() -> None:
    tilt = 0.2  # rad about x
    q = (math.sin(tilt / 2), 0.0, 0.0, math.cos(tilt / 2))
    with pytest.raises(Ros2DecodeError) as e:
        grid_to_ism(cdr.decode_occupancy_grid(_rosbags_grid(np.zeros(6), 3, 2, q=q)))
    assert e.value.code == "non_planar"
    with pytest.raises(Ros2DecodeError) as e:
        grid_to_ism(cdr.decode_occupancy_grid(_rosbags_grid(np.zeros(6), 3, 2,
                                                            q=(0.0, 0.0, 0.0, 0.0))))
    assert e.value.code == "bad_quaternion"
    # a pure yaw of 180 deg is planar (w = 0)
    assert quaternion_yaw((0.0, 0.0, 1.0, 0.0)) == pytest.approx(math.pi)


def test_window_to_grid_and_back_through_rosbags() -> None:
    geom = GridGeometry(0.1, 3, 2, Pose2D(4.0, 5.0, 0.25))
    logodds = np.array([[0.0, 2.0, -2.0], [10.0, -10.0, 0.0]])
    g = window_to_grid(logodds, geom, kind="logodds", frame="map", stamp=3.25)
    raw = cdr.encode_occupancy_grid(g)
    m = TS.deserialize_cdr(raw, "nav_msgs/msg/OccupancyGrid")  # read with rosbags
    expect = [-1, round(100 / (1 + math.exp(-2))), round(100 / (1 + math.exp(2))), 100, 0, -1]
    assert m.data.tolist() == expect
    assert (m.info.width, m.info.height) == (3, 2)
    assert m.info.origin.position.x == 4.0 and m.info.origin.position.y == 5.0
    assert m.info.origin.orientation.z == pytest.approx(math.sin(0.125))
    assert m.header.stamp.sec == 3 and m.header.stamp.nanosec == 250_000_000
    fixed = window_to_grid(np.array([[0, 1000, -1000]], np.int16), GridGeometry(0.1, 3, 1),
                           kind="fixed")
    assert fixed.data.tolist() == [[-1, 73, 27]]
    probs = window_to_grid(np.array([[0.5, 0.9, 0.0]]), GridGeometry(0.1, 3, 1),
                           kind="probability")
    assert probs.data.tolist() == [[-1, 90, 0]]


# -- poses and TF ---------------------------------------------------------------------------
def test_pose_stamped_from_rosbags_and_wrong_frame() -> None:
    T = TS.types
    yaw = -1.2
    msg = T["geometry_msgs/msg/PoseStamped"](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
            sec=5, nanosec=0), frame_id="map"),
        pose=T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=1.0, y=2.0, z=0.3),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2),
                                                          w=math.cos(yaw / 2))))
    raw = bytes(TS.serialize_cdr(msg, "geometry_msgs/msg/PoseStamped"))
    p = pose_to_robot(cdr.decode_pose_stamped(raw), "robot1")
    assert (p.robot, p.x, p.y, p.stamp) == ("robot1", 1.0, 2.0, 5.0)
    assert p.yaw == pytest.approx(yaw)
    with pytest.raises(Ros2DecodeError) as e:
        pose_to_robot(cdr.decode_pose_stamped(raw), "robot1", map_frame="world")
    assert e.value.code == "wrong_frame"


def _tf(parent: str, child: str, x: float, y: float, yaw: float, stamp: float) -> object:
    T = TS.types
    return T["geometry_msgs/msg/TransformStamped"](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
            sec=int(stamp), nanosec=0), frame_id=parent),
        child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=x, y=y, z=0.0),
            rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2),
                                                       w=math.cos(yaw / 2))))


def test_tf_chain_composes_map_odom_base_link() -> None:
    raw = bytes(TS.serialize_cdr(TS.types["tf2_msgs/msg/TFMessage"](transforms=[
        _tf("map", "robot1/odom", 10.0, 0.0, math.pi / 2, 7),
        _tf("robot1/odom", "robot1/base_link", 1.0, 0.0, 0.1, 8),
    ]), "tf2_msgs/msg/TFMessage"))
    tree = TfTree("map", "{robot}/base_link")
    poses = tree.update(cdr.decode_tf_message(raw))
    assert len(poses) == 1
    p = poses[0]
    expect = Pose2D(10.0, 0.0, math.pi / 2).compose(Pose2D(1.0, 0.0, 0.1))
    assert p.robot == "robot1" and p.stamp == 8.0
    assert (p.x, p.y) == (pytest.approx(expect.x), pytest.approx(expect.y))
    assert p.yaw == pytest.approx(expect.yaw)
    # a later odom -> base_link update moves the robot; an unrelated frame does not emit it
    moved = tree.update([cdr.TransformFields("robot1/odom", "robot1/base_link", 9.0,
                                             (2.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))])
    assert moved[0].x == pytest.approx(10.0) and moved[0].y == pytest.approx(2.0)
    assert tree.update([cdr.TransformFields("map", "other", 9.0, (0.0, 0.0, 0.0),
                                            (0.0, 0.0, 0.0, 1.0))]) == []
    small = TfTree(max_frames=2)
    with pytest.raises(Ros2DecodeError) as e:
        small.set([cdr.TransformFields("map", f"f{i}", 0.0, (0.0, 0.0, 0.0),
                                       (0.0, 0.0, 0.0, 1.0)) for i in range(3)])
    assert e.value.code == "too_many_frames" and len(small) == 2


# -- the published region and snapshot -----------------------------------------------------
def test_publish_region_and_snapshot() -> None:
    from sogm_service.adapters.ros2.views import map_snapshot, publish_region
    from sogm_service.core.map.tiles import TiledMap, TileLattice
    from sogm_service.service.server import pipeline
    from sogm_service.wire.messages import IsmMessage, PoseModel

    tiled = TiledMap("m", "map", TileLattice(0.05, 64))
    assert publish_region(tiled, mode="known") is None
    assert publish_region(tiled, [], mode="robots") is None
    for name, fill in (("a", 90), ("b", 20)):
        pipeline.fuse_ism(tiled, IsmMessage(resolution=0.05, width=4, height=4,
                                            encoding="occupancy_i8", data=bytes([fill]) * 16,
                                            origin=PoseModel(x=0.1, y=0.1)), name)
    known = publish_region(tiled, mode="known")
    assert known == GridGeometry(0.05, 64, 64, Pose2D(0.0, 0.0, 0.0))  # the one tile
    small = publish_region(tiled, mode="known", max_cells=100)
    assert small is not None and small.width * small.height <= 100
    assert small.width == small.height == 10 and small.origin.x == pytest.approx(27 * 0.05)
    window = GridGeometry(0.05, 8, 8, Pose2D(0.0, 0.0, 0.0))
    stack = tiled.sample(window, ["a", "b"], "nearest")
    snap = map_snapshot(tiled, window, method="bayes", layers=["b"], fused_layers=["a", "b"])
    assert set(snap.layers) == {"b"} and snap.fused is not None
    total = stack.astype(np.int32).sum(axis=0)
    p = 1 / (1 + np.exp(-total / 1000.0))
    expect = np.where(total == 0, -1, np.rint(p * 100)).astype(np.int8)
    assert np.array_equal(snap.fused.data, expect)
    assert snap.fused.data[3, 3] == round(100 / (1 + (0.1 / 0.9) * (0.8 / 0.2)))  # P_B
