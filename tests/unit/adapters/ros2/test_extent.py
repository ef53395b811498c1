"""Where the ROS 2 maps are published (adapters/ros2/extent): the region of recent changes and
an extent that grows with headroom."""

from __future__ import annotations

import numpy as np

from sogm_service.adapters.ros2.extent import (
    RegionTracker,
    cells_of,
    known_box,
    stable_extent,
)
from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice
from sogm_service.core.map.tiles import TiledMap
from sogm_service.service.server import pipeline
from sogm_service.wire.messages import IsmMessage, PoseModel

RES = 0.05


def _g(u0: int, v0: int, w: int, h: int) -> GridGeometry:
    return GridGeometry(RES, w, h, Pose2D(u0 * RES, v0 * RES, 0.0))


def _ism(tiled: TiledMap, layer: str, x: float, y: float, n: int, fill: int = 90) -> None:
    pipeline.fuse_ism(tiled, IsmMessage(resolution=RES, width=n, height=n,
                                        encoding="occupancy_i8", data=bytes([fill]) * (n * n),
                                        origin=PoseModel(x=x, y=y)), layer)


def test_known_box_is_the_box_of_cells_any_plane_knows() -> None:
    a, b = np.zeros((8, 8), np.int16), np.zeros((8, 8), np.int16)
    assert known_box([a, b]) is None and known_box([]) is None
    a[2, 3], b[5, 1] = 7, -4
    assert known_box([a, b]) == (2, 1, 6, 4)  # rows 2..5, columns 1..3


def test_the_tracker_reports_the_known_cells_of_tiles_changed_since_its_last_call() -> None:
    tiled = TiledMap("m", "map", TileLattice(RES, 64))
    tracker = RegionTracker()
    assert tracker.changed(tiled) is None
    _ism(tiled, "robot1/obstacle", 0.5, 0.25, 10)  # cells u 10..19, v 5..14
    assert tracker.changed(tiled) == (10, 5, 20, 15)
    assert tracker.changed(tiled) is None  # nothing changed since
    _ism(tiled, "robot2/obstacle", 5.0, 4.0, 4)  # another tile: only that one is reported
    assert tracker.changed(tiled) == (100, 80, 104, 84)
    # an ISM of only unknown cells changes no known cell: nothing to hold
    _ism(tiled, "robot3/obstacle", 9.0, 9.0, 4, fill=0xFF)
    assert tracker.changed(tiled) is None


def test_a_growing_side_gets_headroom_so_growths_are_few() -> None:
    first = stable_extent(None, _g(10, 20, 100, 50), step=32, max_cells=10**7, headroom=0.5)
    assert cells_of(first) == (0, 0, 128, 96)  # the first need, rounded out
    grown = stable_extent(first, _g(100, 10, 60, 50), step=32, max_cells=10**7, headroom=0.5)
    # only the east side moves: to the need's end plus half the union's width, rounded out
    assert cells_of(grown) == (0, 0, 256, 96)
    assert stable_extent(grown, _g(200, 0, 40, 90), step=32, max_cells=10**7,
                         headroom=0.5) is grown  # the headroom holds the next need
    # a map explored outwards step by step: a few growths, not one per step
    extent, growths = None, 0
    for k in range(1, 41):
        new = stable_extent(extent, _g(0, 0, 32 * k, 64), step=32, max_cells=10**7,
                            headroom=0.5)
        growths += extent is not None and new is not extent
        extent = new
    assert growths <= 6 and extent is not None and extent.width < 1.6 * 32 * 40


def test_headroom_gives_way_to_max_cells() -> None:
    cur = _g(0, 0, 100, 100)
    grown = stable_extent(cur, _g(50, 0, 100, 100), step=1, max_cells=160 * 100, headroom=0.5)
    assert cells_of(grown) == (0, 0, 150, 100)  # the bare union: headroom would pass the bound
