"""CDR of nav_msgs/OccupancyGrid (adapters/ros2/cdr): bad bytes and bad contents refused with
their codes.

Its ``rosbags_grid`` and typestore ``TS`` serve the other ROS 2 adapter tests.

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

from rosbags.typesys import Stores, get_typestore  # noqa: E402

from sogm_service.adapters.ros2 import Ros2DecodeError, cdr  # noqa: E402
from sogm_service.adapters.ros2.convert import grid_to_ism  # noqa: E402

TS = get_typestore(Stores.ROS2_JAZZY)


def rosbags_grid(data: np.ndarray, width: int, height: int, *, res: float = 0.05,
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


@pytest.mark.parametrize(("mutate", "code"), [
    (lambda raw: raw[:-5], "bad_cdr"),
    (lambda raw: b"", "bad_cdr"),
    (lambda raw: b"\x00\x01\x00\x00" + b"\xff" * 64, "bad_cdr"),
    (lambda raw: b"\x07\x07\x00\x00" + raw[4:], "bad_cdr"),
    (lambda raw: raw[:12] + b"\xff\xff\xff\x7f" + raw[16:], "bad_cdr"),  # frame_id length
    (lambda raw: raw[:-10] + b"\xff\xff\xff\x7f" + raw[-6:], "bad_cdr"),  # data length
])
def test_bad_cdr_is_refused(mutate, code: str) -> None:  # type: ignore[no-untyped-def]
    raw = rosbags_grid(np.zeros(6), 3, 2)
    with pytest.raises(Ros2DecodeError) as e:
        cdr.decode_occupancy_grid(mutate(raw))
    assert e.value.code == code


def test_grid_content_errors_have_their_codes() -> None:
    with pytest.raises(Ros2DecodeError) as e:  # 6 cells for 3x3
        cdr.decode_occupancy_grid(rosbags_grid(np.zeros(6), 3, 3))
    assert e.value.code == "data_length"
    with pytest.raises(Ros2DecodeError) as e:
        cdr.decode_occupancy_grid(rosbags_grid(np.zeros(6), 3, 2), max_cells=5)
    assert e.value.code == "too_large"
    with pytest.raises(Ros2DecodeError) as e:
        cdr.decode_occupancy_grid(rosbags_grid(np.zeros(6), 3, 2), max_bytes=10)
    assert e.value.code == "too_large"
    with pytest.raises(Ros2DecodeError) as e:  # 101 and -5 are not occupancy values
        grid_to_ism(cdr.decode_occupancy_grid(rosbags_grid([0, 101, -5, 0, 0, 0], 3, 2)))
    assert e.value.code == "out_of_range"
    with pytest.raises(Ros2DecodeError) as e:
        grid_to_ism(cdr.decode_occupancy_grid(rosbags_grid(np.zeros(6), 3, 2, res=0.0)))
    assert e.value.code == "non_positive_resolution"
    with pytest.raises(Ros2DecodeError) as e:
        cdr.decode_occupancy_grid(rosbags_grid(np.zeros(6), 3, 2, x=math.nan))
    assert e.value.code == "non_finite"
