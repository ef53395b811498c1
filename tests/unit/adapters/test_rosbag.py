"""ROS bags (adapters/rosbag): bags written with rosbags, ROS 2 and ROS 1, read back as scans
with their TF poses and as grids.

Its ``write_bag`` serves the integration test of the bag replay too."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("rosbags")  # the [ros2] extra
yaml = pytest.importorskip("yaml")

from rosbags.typesys import Stores, get_typestore  # noqa: E402

from sogm_service.adapters.rosbag import BagGrid, BagReader, BagScan  # noqa: E402
from sogm_service.core.geometry import Pose2D  # noqa: E402

TS = get_typestore(Stores.ROS2_JAZZY)


def _ros1_typestore() -> Any:
    from rosbags.typesys import get_types_from_msg

    ts = get_typestore(Stores.ROS1_NOETIC)
    ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                   "tf2_msgs/msg/TFMessage"))
    return ts


def _header(ts: Any, frame: str, t: float) -> object:
    T = ts.types
    sec = int(t)
    stamp = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=round((t - sec) * 1e9))
    if "seq" in dict(ts.fielddefs["std_msgs/msg/Header"][1]):  # ROS 1
        return T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)
    return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)


def _tf_msg(ts: Any, parent: str, child: str, x: float, y: float, yaw: float,
            t: float) -> object:
    T = ts.types
    return T["tf2_msgs/msg/TFMessage"](transforms=[T["geometry_msgs/msg/TransformStamped"](
        header=_header(ts, parent, t), child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=x, y=y, z=0.0),
            rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2),
                                                       w=math.cos(yaw / 2))))])


def _scan(ts: Any, t: float) -> object:
    T = ts.types
    return T["sensor_msgs/msg/LaserScan"](
        header=_header(ts, "robot1/laser", t), angle_min=-0.5, angle_max=0.5,
        angle_increment=0.5, time_increment=0.0, scan_time=0.1, range_min=0.1, range_max=10.0,
        ranges=np.array([1.0, 0.05, 12.0], dtype=np.float32),
        intensities=np.zeros(0, dtype=np.float32))


def _grid(ts: Any, t: float) -> object:
    T = ts.types
    return T["nav_msgs/msg/OccupancyGrid"](
        header=_header(ts, "map", t),
        info=T["nav_msgs/msg/MapMetaData"](
            map_load_time=T["builtin_interfaces/msg/Time"](sec=0, nanosec=0), resolution=0.05,
            width=2, height=2, origin=T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=3.0, y=4.0, z=0.0),
                orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))),
        data=np.array([0, 100, -1, 42], dtype=np.int8))


def write_bag(path: Path, ros1: bool) -> None:
    """A small bag with rosbags' own writer: static + dynamic TF, two scans, one grid."""
    ts = _ros1_typestore() if ros1 else TS
    records = [
        ("/tf_static", "tf2_msgs/msg/TFMessage", 1.0,
         _tf_msg(ts, "robot1/base_link", "robot1/laser", 0.2, 0.0, 0.0, 0.0)),
        ("/scan", "sensor_msgs/msg/LaserScan", 1.5, _scan(ts, 1.5)),  # before any map pose
        ("/tf", "tf2_msgs/msg/TFMessage", 2.0,
         _tf_msg(ts, "map", "robot1/base_link", 1.0, 2.0, math.pi / 2, 2.0)),
        ("/scan", "sensor_msgs/msg/LaserScan", 2.5, _scan(ts, 2.5)),
        ("/ism/robot1/floor", "nav_msgs/msg/OccupancyGrid", 3.0, _grid(ts, 3.0)),
    ]
    if ros1:
        from rosbags.rosbag1 import Writer as Writer1

        with Writer1(path) as w1:
            conns = {}
            for topic, typ, t, msg in records:
                if topic not in conns:
                    conns[topic] = w1.add_connection(topic, typ, typestore=ts)
                w1.write(conns[topic], int(t * 1e9), ts.serialize_ros1(msg, typ))
    else:
        from rosbags.rosbag2 import Writer as Writer2

        with Writer2(path, version=9) as w2:
            conns = {}
            for topic, typ, t, msg in records:
                if topic not in conns:
                    conns[topic] = w2.add_connection(topic, typ, typestore=ts)
                w2.write(conns[topic], int(t * 1e9), ts.serialize_cdr(msg, typ))


@pytest.mark.parametrize("ros1", [False, True], ids=["ros2", "ros1"])
def test_rosbag_scans_with_tf_poses_and_grids(tmp_path: Path, ros1: bool) -> None:
    bag = tmp_path / ("b.bag" if ros1 else "b")
    write_bag(bag, ros1)
    with BagReader(bag) as reader:
        assert len(reader) == reader.total == 5
        items = list(reader)
        stats = reader.stats
    assert stats.messages == 5 and stats.unlocalized == 1 and stats.transforms == 2
    scans = [i for i in items if isinstance(i, BagScan)]
    grids = [i for i in items if isinstance(i, BagGrid)]
    assert len(scans) == 1 and len(grids) == 1
    s = scans[0]
    assert s.position == 4 and s.topic == "/scan" and s.scan.stamp == pytest.approx(2.5)
    expect = Pose2D(1.0, 2.0, math.pi / 2).compose(Pose2D(0.2, 0.0, 0.0))
    assert (s.scan.pose.x, s.scan.pose.y) == (pytest.approx(expect.x), pytest.approx(expect.y))
    assert s.scan.pose.yaw == pytest.approx(math.pi / 2)
    assert s.scan.angles.tolist() == pytest.approx([-0.5, 0.0, 0.5])
    assert s.scan.max_range == 10.0
    r = s.scan.ranges
    assert r[0] == 1.0 and math.isnan(r[1]) and r[2] == 12.0  # below range_min dropped
    g = grids[0]
    assert (g.layer, g.ism.robot, g.position) == ("robot1/floor", "robot1", 5)
    assert g.ism.resolution == 0.05 and (g.ism.origin.x, g.ism.origin.y) == (3.0, 4.0)
    assert g.ism.array().tolist() == [[0, 100], [-1, 42]]
