"""Changed rectangles of a published grid (adapters/ros2/updates), the stable extent
(adapters/ros2/views.stable_extent) and the CDR of map_msgs/msg/OccupancyGridUpdate, checked
against a message built by rosbags from the definition text, never by the adapter's encoder."""

from __future__ import annotations

import numpy as np
import pytest

rosbags = pytest.importorskip("rosbags")  # the [ros2] extra
pytest.importorskip("xxhash")

from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: E402

from sogm_service.adapters.ros2 import Ros2DecodeError, cdr, keys  # noqa: E402
from sogm_service.adapters.ros2.cdr import OccupancyGridFields  # noqa: E402
from sogm_service.adapters.ros2.extent import stable_extent  # noqa: E402
from sogm_service.adapters.ros2.updates import (  # noqa: E402
    Rect,
    apply_update,
    changed_rects,
    grid_update,
)
from sogm_service.core.geometry import GridGeometry, Pose2D  # noqa: E402

UPDATE = "map_msgs/msg/OccupancyGridUpdate"
# map_msgs/msg/OccupancyGridUpdate.msg (ROS 2 navigation_msgs), and the hash `ros2 topic info -v`
# prints for it on Jazzy.
DEFINITION = "std_msgs/Header header\nint32 x\nint32 y\nuint32 width\nuint32 height\nint8[] data\n"
ROS_HASH = "RIHS01_c4095b0be2e4363f8978a1570e0293ee093436f1e1c61d99b48502ac317025e8"

TS = get_typestore(Stores.ROS2_JAZZY)
TS.register(get_types_from_msg(DEFINITION, UPDATE))


def test_the_type_hash_is_rosbags_rihs01_of_the_definition() -> None:
    assert TS.hash_rihs01(UPDATE) == ROS_HASH == keys.type_hash(keys.OCCUPANCY_GRID_UPDATE)
    assert keys.topic_key(0, "/sogm/m/map_updates", keys.OCCUPANCY_GRID_UPDATE) == \
        f"0/sogm/m/map_updates/map_msgs::msg::dds_::OccupancyGridUpdate_/{ROS_HASH}"


def test_update_cdr_is_rosbags_bytes_both_ways() -> None:
    data = np.arange(-1, 11, dtype=np.int8).reshape(3, 4)
    u = cdr.GridUpdateFields("map", 12.5, 7, 9, 4, 3, data)
    T = TS.types
    want = bytes(TS.serialize_cdr(T[UPDATE](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
            sec=12, nanosec=500_000_000), frame_id="map"),
        x=7, y=9, width=4, height=3, data=data.ravel()), UPDATE))
    assert cdr.encode_grid_update(u) == want
    back = cdr.decode_grid_update(want)
    assert (back.frame, back.stamp, back.x, back.y, back.width, back.height) == \
        ("map", 12.5, 7, 9, 4, 3)
    assert np.array_equal(back.data, data)
    short = bytes(TS.serialize_cdr(T[UPDATE](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
            sec=0, nanosec=0), frame_id="map"),
        x=0, y=0, width=5, height=5, data=data.ravel()), UPDATE))
    with pytest.raises(Ros2DecodeError) as e:
        cdr.decode_grid_update(short)
    assert e.value.code == "data_length"
    with pytest.raises(Ros2DecodeError) as e:
        cdr.decode_grid_update(want[:20])
    assert e.value.code == "bad_cdr"


def _grid(data: np.ndarray) -> OccupancyGridFields:
    h, w = data.shape
    return OccupancyGridFields("map", 1.0, 0.05, w, h, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0),
                               data)


def _apply_all(old: np.ndarray, new: np.ndarray, rects: list[Rect]) -> np.ndarray:
    held = old.copy()
    for r in rects:
        assert apply_update(held, grid_update(_grid(new), r))
    return held


def test_no_change_no_rectangle() -> None:
    a = np.full((300, 200), -1, np.int8)
    assert changed_rects(a, a.copy()) == []


def test_rectangles_cover_the_change_tightly_and_applying_them_gives_the_new_grid() -> None:
    rng = np.random.default_rng(2)
    old = rng.integers(0, 101, size=(512, 384)).astype(np.int8)
    new = old.copy()
    new[10:20, 30:45] = 77  # inside one block
    new[100:170, 60:200] = 5  # across blocks and block rows
    new[511, 383] = -1  # the last cell
    rects = changed_rects(old, new, block=64)
    assert np.array_equal(_apply_all(old, new, rects), new)
    assert Rect(30, 10, 15, 10) in rects and Rect(383, 511, 1, 1) in rects
    changed = int(np.count_nonzero(old != new))
    assert sum(r.cells for r in rects) < 1.2 * changed  # bytes follow the change
    covered = np.zeros(old.shape, np.int16)
    for r in rects:
        covered[r.y:r.y + r.height, r.x:r.x + r.width] += 1
    assert covered.max() == 1  # no two overlap: any order gives the same grid


def test_a_scattered_change_is_one_rectangle_per_row_of_blocks() -> None:
    old = np.zeros((256, 256), np.int8)
    new = old.copy()
    new[::8, ::8] = 1  # every other block of 4 x 4 cells: 32 x 32 runs
    rects = changed_rects(old, new, block=4, max_rects=64)
    assert len(rects) == 32 and all(r.width == 249 and r.height == 1 for r in rects)
    assert np.array_equal(_apply_all(old, new, rects), new)


def test_an_update_outside_the_grid_is_not_applied() -> None:
    held = np.zeros((4, 4), np.int8)
    u = cdr.GridUpdateFields("map", 0.0, 3, 0, 2, 1, np.ones((1, 2), np.int8))
    assert not apply_update(held, u) and not held.any()


def _g(u0: int, v0: int, w: int, h: int, res: float = 0.05) -> GridGeometry:
    return GridGeometry(res, w, h, Pose2D(u0 * res, v0 * res, 0.0))


def test_the_extent_grows_in_whole_tiles_and_never_shrinks_or_moves() -> None:
    first = stable_extent(None, _g(10, 20, 100, 50), step=64, max_cells=10**6)
    assert first == _g(0, 0, 128, 128)
    assert stable_extent(first, _g(30, 30, 20, 20), step=64, max_cells=10**6) is first
    grown = stable_extent(first, _g(100, -10, 100, 50), step=64, max_cells=10**6)
    assert grown == _g(0, -64, 256, 192)  # the union, rounded out
    assert stable_extent(grown, _g(5, 5, 10, 10), step=64, max_cells=10**6) is grown


def test_past_max_cells_the_extent_stays_while_it_holds_the_need_then_moves() -> None:
    cur = _g(0, 0, 128, 128)
    # growing would pass the bound; the needed window's centre is still inside: it stays
    assert stable_extent(cur, _g(32, 32, 128, 128), step=64, max_cells=128 * 128) is cur
    # the needed window has left it: placed anew on the need, rounded out
    moved = stable_extent(cur, _g(1000, 0, 100, 100), step=64, max_cells=200 * 200)
    assert moved == _g(960, 0, 192, 128)
    # rounding out would pass the bound: the need itself
    assert stable_extent(None, _g(1, 1, 100, 100), step=64, max_cells=100 * 100) == \
        _g(1, 1, 100, 100)
