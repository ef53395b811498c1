"""Simulator: seeded worlds, robots and sensors; sensor ISMs against ground truth."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from sogm_service.core.geometry import Pose2D
from sogm_service.sim.offline import map_world
from sogm_service.sim.robots import SimStep, simulate
from sogm_service.sim.sensors import SemanticCamera, TiltedLaser, default_sensors, lookup
from sogm_service.sim.worlds import World, tabletop_world, warehouse_world


@pytest.fixture(scope="module")
def table() -> World:
    return tabletop_world(3)


@pytest.fixture(scope="module")
def warehouse() -> World:
    return warehouse_world(5)


def test_worlds_are_deterministic_by_seed() -> None:
    a, b, c = tabletop_world(1), tabletop_world(1), tabletop_world(2)
    assert np.array_equal(a.labels, b.labels) and np.array_equal(a.heights, b.heights)
    assert not np.array_equal(a.labels, c.labels)
    w1, w2 = warehouse_world(1), warehouse_world(2)
    assert np.array_equal(w1.labels, warehouse_world(1).labels)
    assert not np.array_equal(w1.labels, w2.labels)


def test_tabletop_world_layout(table: World) -> None:
    assert table.classes == ("unknown", "floor", "table", "obstacle")
    assert table.geometry.shape == (300, 300) and table.geometry.resolution == 0.01
    counts = np.bincount(table.labels.ravel(), minlength=4)
    assert (counts > 0).all()
    # The room is closed: no floor cell touches unknown space.
    unknown_near = cv2.dilate((table.labels == 0).astype(np.uint8), np.ones((3, 3), np.uint8))
    assert not (unknown_near.astype(bool) & table.mask("floor")).any()
    assert (table.heights[table.mask("table")] == np.float32(0.75)).all()
    assert (table.heights[table.mask("floor")] == 0).all()


def test_warehouse_world_layout(warehouse: World) -> None:
    assert warehouse.geometry.shape == (800, 1200) and warehouse.geometry.resolution == 0.05
    fractions = np.bincount(warehouse.labels.ravel(), minlength=5) / warehouse.labels.size
    names = dict(zip(warehouse.classes, fractions, strict=True))
    assert names["floor"] > 0.6 and names["shelf"] > 0.05 and names["pallet"] > 0.003
    assert names["wall"] > 0.01
    assert warehouse.drivable().mean() > 0.4


def run(world: World, seed: int, odom_noise: float = 0.0) -> list[SimStep]:
    return list(simulate(world, robots=2, duration_s=3.0, rate_hz=2.0, seed=seed,
                         odom_noise=odom_noise))


def test_simulation_is_deterministic_by_seed(table: World) -> None:
    a, b, c = run(table, 7), run(table, 7), run(table, 8)
    assert [s.robot for s in a] == ["robot1", "robot2"] * 7
    for sa, sb in zip(a, b, strict=True):
        assert sa.true_pose == sb.true_pose and sa.pose == sb.pose
        for ia, ib in zip(sa.isms, sb.isms, strict=True):
            assert ia.layer == ib.layer and ia.geometry == ib.geometry
            assert np.array_equal(ia.prob, ib.prob)
    assert any(sa.true_pose != sc.true_pose for sa, sc in zip(a, c, strict=True))


def test_routes_stay_clear_of_objects(warehouse: World) -> None:
    clear = warehouse.drivable(clearance=warehouse.robot_radius)
    steps = list(simulate(warehouse, robots=3, duration_s=60.0, rate_hz=1.0, seed=2,
                          sensors=[]))
    pts = np.array([[s.true_pose.x, s.true_pose.y] for s in steps])
    uv = warehouse.geometry.world_to_index(pts)
    assert clear[uv[:, 1], uv[:, 0]].all()
    moved = np.linalg.norm(pts[-3:] - pts[:3], axis=1)
    assert (moved > 1.0).all()  # every robot went somewhere


def test_odometry_noise_drifts_only_when_asked(table: World) -> None:
    exact = run(table, 4)
    noisy = run(table, 4, odom_noise=0.05)
    assert all(s.pose == s.true_pose for s in exact)
    drift = [math.hypot(s.pose.x - s.true_pose.x, s.pose.y - s.true_pose.y) for s in noisy]
    assert drift[0] == 0 and max(drift) > 1e-4
    assert [s.true_pose for s in exact] == [s.true_pose for s in noisy]
    # ISMs are published where the robot believes it is: at the reported (drifted) pose.
    for s in noisy:
        laser_ism = s.isms[0]
        assert laser_ism.layer == "obstacle"
        assert math.isclose(math.remainder(laser_ism.geometry.origin.yaw - s.pose.yaw, math.tau),
                            0.0, abs_tol=1e-9)


def test_laser_ism_agrees_with_ground_truth(warehouse: World) -> None:
    laser = TiltedLaser()
    empty = (~warehouse.occupied).astype(np.uint8)
    obstacle_dist = cv2.distanceTransform(empty, cv2.DIST_L2, 5) * warehouse.geometry.resolution
    steps = list(simulate(warehouse, robots=2, duration_s=10.0, rate_hz=1.0, seed=9,
                          sensors=[laser]))
    n_occ = 0
    for step in steps:
        (ism,) = step.isms
        assert ism.layer == "obstacle" and max(ism.geometry.shape) <= 256
        centres = ism.geometry.cell_centers()
        d, inside = lookup(warehouse, centres, obstacle_dist)
        occ, free = ism.prob > 0.5, ism.prob < 0.5
        # Hits lie on objects within the noise model (3 sigma + one ISM cell + half a world cell).
        tol = 3 * laser.range_noise + 1.5 * laser.resolution
        assert (d[occ] <= tol).all()
        # Free cells are free in the world (allow a cell of rasterisation at object edges).
        assert (d[free & inside] > 0).mean() > 0.99
        n_occ += int(occ.sum())
    assert n_occ > 100


def test_tilted_laser_sees_low_pallets_only_far_away(warehouse: World) -> None:
    laser = TiltedLaser()
    # The beam descends 5 cm per metre from 30 cm: a 15 cm pallet is hit only beyond 3 m.
    low = 0.15
    assert laser.height - 3.0 * math.tan(laser.pitch) == pytest.approx(low, abs=1e-9)
    floor_world = World(np.ones((100, 200), np.uint8), warehouse.classes,
                        type(warehouse.geometry)(0.05, 200, 100, Pose2D()),
                        np.zeros((100, 200), np.float32))
    for x, expect_hit in ((2.0, False), (4.0, True)):
        heights = floor_world.heights.copy()
        heights[:, round(x / 0.05):] = low + 0.001
        w = World(floor_world.labels, floor_world.classes, floor_world.geometry, heights)
        ranges, _ = laser.scan(w, Pose2D(0.0, 2.5, 0.0), np.random.default_rng(0))
        mid = ranges[len(ranges) // 2]
        if expect_hit:
            assert mid == pytest.approx(x, abs=0.1)
        else:
            assert mid >= 3.0 - 0.1  # passes over at 2 m and meets the pallet only at 3 m


@pytest.mark.parametrize("confusion", [0.0, 0.2])
def test_camera_labels_agree_with_ground_truth_up_to_confusion(table: World,
                                                               confusion: float) -> None:
    cam = SemanticCamera(classes=("floor", "table"), height=1.0, near=0.15, far=1.2,
                         hfov=math.radians(60), resolution=0.02, confusion=confusion)
    assert cam.resolution > table.geometry.resolution  # coarser than the map
    steps = list(simulate(table, robots=2, duration_s=10.0, rate_hz=1.0, seed=1, sensors=[]))
    wrong = seen = 0
    for i, step in enumerate(steps):
        geom, labels, visible = cam.observe(table, step.true_pose, np.random.default_rng(i))
        truth, _ = lookup(table, geom.cell_centers(), table.labels)
        wrong += int((labels != truth)[visible].sum())
        seen += int(visible.sum())
        assert (truth[visible] != 0).all()
    rate = wrong / seen
    assert seen > 20000
    sigma = math.sqrt(max(confusion * (1 - confusion), 1e-12) / seen)
    assert abs(rate - confusion) < 5 * sigma + 1e-12


def test_camera_isms_encode_labels(table: World) -> None:
    cam = default_sensors(table)[1]
    assert isinstance(cam, SemanticCamera)
    pose = next(iter(simulate(table, 1, 0.0, 1.0, seed=3, sensors=[]))).true_pose
    _, labels, visible = cam.observe(table, pose, np.random.default_rng(5))
    isms = cam.isms(table, pose, pose, np.random.default_rng(5))
    assert [i.layer for i in isms] == ["floor", "table"]
    for ism in isms:
        k = table.class_index(ism.layer)
        assert ((ism.prob == np.float32(cam.p_hit)) == (visible & (labels == k))).all()
        assert ((ism.prob == 0.5) == ~visible).all()
        assert max(ism.geometry.shape) <= 256


def test_default_cameras_are_coarser_than_the_map(table: World, warehouse: World) -> None:
    for world in (table, warehouse):
        cams = [s for s in default_sensors(world) if isinstance(s, SemanticCamera)]
        assert cams and all(c.resolution > world.geometry.resolution for c in cams)


def test_map_world_matches_ground_truth(table: World) -> None:
    layers, p = map_world(table, seed=0, robots=2, duration_s=60.0)
    assert layers == ["obstacle", "floor", "table"]
    assert p.shape == (3, *table.geometry.shape) and p.dtype == np.float32
    inner = cv2.erode(table.mask("floor").astype(np.uint8) | table.mask("table")
                      | (table.heights > 0) & (table.labels != 0), np.ones((5, 5), np.uint8))
    # Judge cells away from class borders (one ISM cell of blur is expected there).
    borders = cv2.morphologyEx(table.labels, cv2.MORPH_GRADIENT, np.ones((5, 5), np.uint8)) > 0
    judged = inner.astype(bool) & ~borders
    truth = {"obstacle": table.occupied, "floor": table.mask("floor"), "table": table.mask("table")}
    for n, name in enumerate(layers):
        seen = judged & (p[n] != 0.5)
        assert seen.sum() > 0.5 * judged.sum(), name
        agree = ((p[n] > 0.5) == truth[name])[seen].mean()
        assert agree > 0.95, (name, agree)
    assert (p[:, table.labels == 0] == 0.5).mean() > 0.95  # outside the room stays unknown
