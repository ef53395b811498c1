"""Evidence lands where the sensor put it: laser ISMs cast on the map lattice
(adapters/laser_lattice).

The project's map is compared with an independent ray-casting log-odds mapper
(:mod:`tests.raycast_reference`: Bresenham per beam on the map lattice, the same range rules)
on synthetic scans and on the Intel log.  Targets: occupied IoU >= 0.85 and cells marked free
where the reference says unknown <= 1 % of the observed cells.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import pytest

from sogm_service.adapters.carmen import LaserScan, read_carmen, scan_ism
from sogm_service.adapters.laser import encode_occupancy_i8, laser_ism
from sogm_service.adapters.laser_lattice import laser_ism_on_lattice, scan_ism_on_lattice
from sogm_service.core import logodds
from sogm_service.core.geometry import Pose2D, TileLattice
from sogm_service.core.map.tiles import TiledMap
from sogm_service.core.resample import lattice_offset, tile_patches
from sogm_service.sim.sensors import TiltedLaser
from tests.helpers import INTEL_LOG, needs_intel
from tests.raycast_reference import Comparison, compare, reference_map

RES = 0.05
USABLE = 20.0
DEVICE_MAX = 80.0


# -- synthetic scans ------------------------------------------------------------------------
def _walls() -> npt.NDArray[np.float64]:
    """Segments ``(x0, y0, x1, y1)``: a 12 x 8 m room with a 2 m door on the east wall (a
    corridor beyond it ends at a far wall 30 m away), a gap in the north wall opening onto
    nothing (no return), a pillar and a slanted wall."""
    segs = [
        (0, 0, 12, 0), (12, 0, 12, 3), (12, 5, 12, 8), (12, 8, 7, 8), (5, 8, 0, 8),
        (0, 8, 0, 0),
        (12, 3, 40, 3), (12, 5, 40, 5), (40, 3, 40, 5),  # corridor to a wall 28 m east
        (4, 3, 5, 3), (5, 3, 5, 4), (5, 4, 4, 4), (4, 4, 4, 3),  # pillar
        (8, 1, 10.5, 2.7),  # slanted wall
    ]
    return np.array(segs, dtype=np.float64)


def _cast(pose: Pose2D, angles: npt.NDArray[np.float64],
          walls: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Exact range of each ray to the nearest segment (inf where none)."""
    a = pose.yaw + angles
    dx, dy = np.cos(a)[:, None], np.sin(a)[:, None]
    x0, y0, x1, y1 = (walls[:, k][None, :] for k in range(4))
    ex, ey = x1 - x0, y1 - y0
    den = dx * ey - dy * ex
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((x0 - pose.x) * ey - (y0 - pose.y) * ex) / den
        s = ((x0 - pose.x) * dy - (y0 - pose.y) * dx) / den
    ok = (np.abs(den) > 1e-12) & (t > 1e-9) & (s >= 0) & (s <= 1)
    return np.where(ok, t, np.inf).min(axis=1)


def synthetic_scans(n: int = 40, seed: int = 0) -> list[LaserScan]:
    """``n`` 181-beam scans from poses inside the room, ranges with 1 cm noise; no return
    (beyond every wall) is the device's 81.9 m."""
    rng = np.random.default_rng(seed)
    walls = _walls()
    angles = np.radians(np.arange(-90.0, 90.5, 1.0))
    scans = []
    for k in range(n):
        pose = Pose2D(float(rng.uniform(1.0, 11.0)), float(rng.uniform(1.0, 7.0)),
                      float(rng.uniform(-math.pi, math.pi)))
        if 3.8 < pose.x < 5.2 and 2.8 < pose.y < 4.2:
            pose = Pose2D(2.0, 6.0, pose.yaw)
        r = _cast(pose, angles, walls) + rng.normal(0.0, 0.01, angles.shape)
        r = np.where(np.isfinite(r), r, 81.9)
        scans.append(LaserScan(float(k), pose, r.astype(np.float32),
                               angles.astype(np.float32), DEVICE_MAX))
    return scans


# -- the project's map and the reference ----------------------------------------------------
def _box(scans: list[LaserScan]) -> tuple[int, int, int, int]:
    xy = np.array([[s.pose.x, s.pose.y] for s in scans])
    lo = np.floor((xy.min(axis=0) - USABLE - 1) / RES).astype(int)
    hi = np.ceil((xy.max(axis=0) + USABLE + 1) / RES).astype(int)
    return int(lo[0]), int(lo[1]), int(hi[0] - lo[0]), int(hi[1] - lo[1])


def project_map(scans: list[LaserScan], grid: str, interp: str = "biodds",
                box: tuple[int, int, int, int] | None = None) -> npt.NDArray[np.int16]:
    """The scans fused by :class:`TiledMap` as ``replay carmen`` sends them (occupancy_i8)."""
    tiled = TiledMap("m", "map", TileLattice(RES, 256))
    for s in scans:
        if grid == "lattice":
            geom, p = scan_ism_on_lattice(s, RES, USABLE)
        else:
            geom, p = scan_ism(s, RES, USABLE)
        inc = logodds.increments(encode_occupancy_i8(p), "occupancy_i8")
        tiled.fuse("obstacle", inc, geom, interp, s.stamp)  # type: ignore[arg-type]
    return tiled.mosaic(box or _box(scans), [0])[0]


def measure(scans: list[LaserScan], grid: str, interp: str = "biodds") -> Comparison:
    box = _box(scans)
    ref = reference_map([(s.pose.x, s.pose.y, s.pose.yaw, s.ranges, s.angles) for s in scans],
                        RES, USABLE, DEVICE_MAX, box)
    return compare(project_map(scans, grid, interp, box), ref)


def meets_targets(c: Comparison) -> bool:
    return c.occupied_iou >= 0.85 and c.free_where_unknown_frac <= 0.01


# -- the lattice ISM itself -----------------------------------------------------------------
def test_lattice_ism_sits_on_the_map_lattice_so_the_server_slices_it() -> None:
    geom, p = laser_ism_on_lattice([3.0, 2.0], [0.3, -1.2], Pose2D(1.234, -5.678, 0.9), RES,
                                   10.0)
    assert geom.origin.yaw == 0.0
    assert lattice_offset(geom, RES) is not None
    inc = logodds.increments(encode_occupancy_i8(p), "occupancy_i8")
    parts = list(tile_patches(inc, geom, TileLattice(RES, 256), "biodds"))
    assert parts and all(np.shares_memory(part.patch, inc) for part in parts)  # slices


def test_one_beam_is_its_cells_exactly() -> None:
    # Sensor in cell (0, 0), a hit 1.0 m east: cells 0..19 free, cell 20 occupied, nothing else.
    geom, p = laser_ism_on_lattice([1.0], [0.0], Pose2D(0.025, 0.025, 0.0), RES, 10.0)
    c0 = round(geom.origin.x / RES)
    r0 = round(geom.origin.y / RES)
    row = p[0 - r0]
    assert np.all(row[0 - c0:20 - c0] == np.float32(0.3))
    assert row[20 - c0] == np.float32(0.8)
    known = p != np.float32(0.5)
    assert np.count_nonzero(known) == 21
    # A reading at the device's no-return value adds nothing; one beyond the usable range is
    # free up to it (end cell included), with no hit.
    _, p2 = laser_ism_on_lattice([80.0, 12.0], [0.0, 0.0], Pose2D(0.025, 0.025, 0.0), RES,
                                 10.0, device_max_range=80.0)
    assert np.count_nonzero(p2 == np.float32(0.8)) == 0
    assert np.count_nonzero(p2 == np.float32(0.3)) == 201  # cells 0..200 (10 m)


def test_diagonal_beam_visits_one_cell_per_step() -> None:
    _, p = laser_ism_on_lattice([math.hypot(0.5, 0.25)], [math.atan2(0.25, 0.5)],
                                   Pose2D(0.025, 0.025, 0.0), RES, 10.0)
    assert np.count_nonzero(p == np.float32(0.3)) == 10  # 10 major-axis steps before the hit
    assert np.count_nonzero(p == np.float32(0.8)) == 1


def test_tilted_laser_can_cast_on_the_lattice() -> None:
    from sogm_service.sim.worlds import warehouse_world

    world = warehouse_world(seed=0)
    laser = TiltedLaser(grid="lattice")
    pose = Pose2D(5.02, 5.03, 0.4)
    (ism,) = laser.isms(world, pose, pose, np.random.default_rng(0))
    assert lattice_offset(ism.geometry, world.geometry.resolution) is not None
    sensor = TiltedLaser().isms(world, pose, pose, np.random.default_rng(0))[0]
    assert sensor.geometry.origin.yaw == pytest.approx(0.4)


# -- against the independent mapper ---------------------------------------------------------
def test_synthetic_scans_meet_the_targets_on_the_lattice_and_not_through_biodds() -> None:
    scans = synthetic_scans()
    sharp = measure(scans, "lattice")
    smeared = measure(scans, "sensor", "biodds")
    print(f"synthetic: lattice {sharp}, sensor+biodds {smeared}")
    assert meets_targets(sharp), sharp
    assert sharp.occupied_iou > smeared.occupied_iou
    assert sharp.free_where_unknown < smeared.free_where_unknown


@needs_intel
def test_intel_log_meets_the_targets_on_the_lattice() -> None:
    scans = list(read_carmen(INTEL_LOG, limit=300))
    sharp = measure(scans, "lattice")
    print(f"intel (300 scans): lattice {sharp}")
    assert meets_targets(sharp), sharp


def test_sensor_aligned_ism_is_unchanged() -> None:
    # The sensor-aligned model stays what it was (the "sensor" grid and the rosbag/eval paths).
    geom, p = laser_ism([1.0], [0.0], Pose2D(0.0, 0.0, 0.3), RES, 10.0)
    assert geom.origin.yaw == pytest.approx(0.3)
    assert np.count_nonzero(p == np.float32(0.8)) == 1
