"""ROS 2 messages to and from the map (adapters/ros2/convert): occupancy grids to ISMs and
windows to grids, poses from PoseStamped and TF chains.

The expected values here are literal strings from rmw_zenoh's wire as documented by the
rmw_zenoh project, or built by hand from its byte layout (struct, xxhash, zenoh-ext's own
serializer) and with rosbags, never with the adapter's encoders.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

rosbags = pytest.importorskip("rosbags")  # the [ros2] extra
xxhash = pytest.importorskip("xxhash")


from sogm_service.adapters.ros2 import Ros2DecodeError, cdr  # noqa: E402
from sogm_service.adapters.ros2.convert import (  # noqa: E402
    TfTree,
    grid_to_ism,
    pose_to_robot,
    quaternion_yaw,
    window_to_grid,
)
from sogm_service.core.geometry import GridGeometry, Pose2D  # noqa: E402
from tests.unit.adapters.ros2.test_cdr import TS, rosbags_grid  # noqa: E402

# -- grids ------------------------------------------------------------------------------------


def test_occupancy_grid_from_rosbags_to_ism() -> None:
    cells = np.array([[0, 100, -1, 50], [25, -1, 0, 100], [1, 2, 3, 4]], dtype=np.int8)
    yaw = 0.4
    raw = rosbags_grid(cells.ravel(), 4, 3, q=(0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)))
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


def test_non_planar_and_degenerate_quaternions_are_refused() -> None:
    tilt = 0.2  # rad about x
    q = (math.sin(tilt / 2), 0.0, 0.0, math.cos(tilt / 2))
    with pytest.raises(Ros2DecodeError) as e:
        grid_to_ism(cdr.decode_occupancy_grid(rosbags_grid(np.zeros(6), 3, 2, q=q)))
    assert e.value.code == "non_planar"
    with pytest.raises(Ros2DecodeError) as e:
        grid_to_ism(cdr.decode_occupancy_grid(rosbags_grid(np.zeros(6), 3, 2,
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
