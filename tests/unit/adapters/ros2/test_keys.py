"""Key expressions, liveliness tokens, QoS strings and type hashes of rmw_zenoh
(adapters/ros2/keys).

The expected values here are literal strings from rmw_zenoh's wire as documented by the
rmw_zenoh project, or built by hand from its byte layout (struct, xxhash, zenoh-ext's own
serializer) and with rosbags, never with the adapter's encoders.
"""

from __future__ import annotations

import pytest

rosbags = pytest.importorskip("rosbags")  # the [ros2] extra
xxhash = pytest.importorskip("xxhash")

from rosbags.typesys import Stores, get_typestore  # noqa: E402
from rosbags.typesys.base import Nodetype  # noqa: E402

from sogm_service.adapters.ros2 import Ros2DecodeError, keys  # noqa: E402
from tests.unit.adapters.ros2.test_cdr import TS  # noqa: E402

SPEC_HASHES = {  # the type hashes rmw_zenoh's documentation lists
    "nav_msgs/msg/OccupancyGrid":
        "RIHS01_8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7",
    "geometry_msgs/msg/PoseStamped":
        "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8",
    "nav_msgs/msg/Odometry":
        "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
    "tf2_msgs/msg/TFMessage":
        "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
}


# The add_two_ints service key of rmw_zenoh's own documentation (a service hash of known value).
ADD_TWO_INTS_HASH = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"


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
    # a class pattern's topic spells its glob characters out
    assert keys.ros_safe_name("*/laser/obstacle") == "all/laser/obstacle"
    assert keys.ros_safe_name("robot?/person") == "robotany/person"
