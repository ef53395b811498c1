"""The map as ROS 2 sees it (adapters/ros2/views): the published region and the snapshot."""

from __future__ import annotations

import numpy as np
import pytest

rosbags = pytest.importorskip("rosbags")  # the [ros2] extra
xxhash = pytest.importorskip("xxhash")


from sogm_service.core.geometry import GridGeometry, Pose2D  # noqa: E402


def test_publish_region_and_snapshot() -> None:
    from sogm_service.adapters.ros2.extent import publish_region
    from sogm_service.adapters.ros2.views import map_snapshot
    from sogm_service.core.geometry import TileLattice
    from sogm_service.core.map.tiles import TiledMap
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


def test_class_patterns_publish_one_grid_per_class_and_pool_classes() -> None:
    from sogm_service.adapters.ros2.views import map_snapshot
    from sogm_service.core.geometry import TileLattice
    from sogm_service.core.map.tiles import TiledMap
    from sogm_service.service.server import pipeline
    from sogm_service.wire.messages import IsmMessage, PoseModel

    tiled = TiledMap("m", "map", TileLattice(0.05, 64))
    # two robots' obstacle layers side by side, overlapping in one column; a person layer
    for name, x, fill in (("robot1/laser/obstacle", 0.0, 20), ("robot2/laser/obstacle", 0.15, 90),
                          ("robot1/person", 0.0, 60)):
        pipeline.fuse_ism(tiled, IsmMessage(resolution=0.05, width=4, height=4,
                                            encoding="occupancy_i8", data=bytes([fill]) * 16,
                                            origin=PoseModel(x=x, y=0.0)), name)
    window = GridGeometry(0.05, 8, 4, Pose2D(0.0, 0.0, 0.0))
    names = ["robot1/laser/obstacle", "robot2/laser/obstacle", "robot1/person"]
    stack = tiled.sample(window, names, "nearest").astype(np.int32)
    snap = map_snapshot(tiled, window, layers=["*/laser/obstacle", "nobody/*"],
                        fused_layers=["*/laser/obstacle", "*/person"], method="max")
    assert set(snap.layers) == {"*/laser/obstacle"}  # a class matching nothing is left out
    obstacle = stack[0] + stack[1]  # the Bayesian rule: log-odds add
    cells = np.asarray(snap.layers["*/laser/obstacle"].data)
    p = 1 / (1 + np.exp(-obstacle / 1000.0))
    assert np.array_equal(cells, np.where(obstacle == 0, -1, np.rint(p * 100)).astype(np.int8))
    assert cells[0, 0] < 50 and cells[0, 7] == -1 and cells[0, 4] > 50  # robot1 free, robot2 occ
    # the fused map pools the classes (max over the classes that observed a cell)
    pooled = np.where(stack[2] != 0, np.maximum(obstacle, stack[2]), obstacle)
    assert snap.fused is not None
    q = 1 / (1 + np.exp(-pooled / 1000.0))
    assert np.array_equal(np.asarray(snap.fused.data),
                          np.where(pooled == 0, -1, np.rint(q * 100)).astype(np.int8))
