"""CARMEN log reader and an offline map of the Intel Research Lab log."""

from __future__ import annotations

import gzip
import itertools
import math
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from sogm_service.adapters.carmen import (
    CarmenStats,
    carmen_angles,
    carmen_guess_fov,
    parse_flaser,
    parse_robotlaser,
    read_carmen,
)
from sogm_service.adapters.laser import scan_endpoints_world
from sogm_service.sim.offline import map_scans
from tests.helpers import INTEL_LOG, needs_intel

GOOD = "FLASER 4 1.0 2.0 81.83 0.5 1.5 -2.0 0.25 9.0 9.0 9.0 123.5 host 124.0\n"


def test_parse_flaser_fields() -> None:
    scan = parse_flaser(GOOD)
    assert scan.ranges.tolist() == [1.0, 2.0, pytest.approx(81.83), 0.5]
    assert (scan.pose.x, scan.pose.y, scan.pose.yaw) == (1.5, -2.0, 0.25)
    assert scan.odom_pose is not None and scan.odom_pose.x == 9.0
    assert scan.stamp == 123.5
    assert scan.max_range == 80.0
    assert scan.angles[0] == pytest.approx(-math.pi / 2)


def test_angles_follow_carmen_guesses() -> None:
    a = carmen_angles(180)
    assert a[0] == pytest.approx(-math.pi / 2)
    assert np.diff(a) == pytest.approx(math.radians(1.0), abs=1e-6)
    assert carmen_angles(361)[-1] == pytest.approx(math.pi / 2, abs=1e-6)
    assert carmen_angles(100)[-1] == pytest.approx(math.pi / 2, abs=1e-6)


@pytest.mark.parametrize("compress", [False, True])
def test_malformed_lines_are_counted_and_skipped(tmp_path: Path, compress: bool) -> None:
    lines = [
        "# comment\n", "PARAM robot_frontlaser_offset 0.0 nohost 0\n", "ODOM 0 0 0 0 0 0 1 h 1\n",
        "FLASER 180 1.0 2.0\n",  # truncated
        GOOD.replace("2.0 81.83", "abc 81.83"),  # not a number
        GOOD.replace("1.5 -2.0", "nan -2.0"),  # non-finite pose
        "FLASER -3 1 2 3 4 5 6 7 8 9 10\n",  # negative count
        "FLASER\n", "\n", "\x00\xff garbage\n",
        GOOD,
    ]
    path = tmp_path / ("log.gz" if compress else "log.txt")
    data = "".join(lines).encode("latin-1")
    path.write_bytes(gzip.compress(data) if compress else data)
    stats = CarmenStats()
    scans = list(read_carmen(path, stats=stats))
    assert len(scans) == 1 and scans[0].pose.x == 1.5
    assert stats.malformed == 5
    assert stats.scans == 1
    assert stats.lines == len(lines)


@needs_intel
def test_intel_log_reads_whole_and_limit() -> None:
    stats = CarmenStats()
    scans = list(read_carmen(INTEL_LOG, stats=stats))
    assert len(scans) == 910 and stats.malformed == 0
    first = scans[0]
    assert first.ranges.shape == (180,) and first.ranges.dtype == np.float32
    assert (first.pose.x, first.pose.y, first.pose.yaw) == pytest.approx(
        (0.600266, -0.0320327, -0.354665))
    assert first.stamp == pytest.approx(32.9068)
    # The log's own stamps step back a little four times; the reader keeps them as they are.
    assert scans[-1].stamp - scans[0].stamp > 2000
    assert len(list(read_carmen(INTEL_LOG, limit=7))) == 7


@needs_intel
def test_intel_slice_map_occupied_on_endpoints_and_corridors_free() -> None:
    scans = list(read_carmen(INTEL_LOG, limit=250))[100:250]
    usable = 15.0
    geom, p = map_scans(scans, resolution=0.05, usable_range=usable)
    ends = np.vstack([scan_endpoints_world(s.ranges, s.angles, s.pose, min(usable, s.max_range))
                      for s in scans])
    uv = geom.world_to_index(ends)
    end_cells = np.zeros(geom.shape, np.uint8)
    end_cells[uv[:, 1], uv[:, 0]] = 1
    ring = np.ones((3, 3), np.uint8)  # one cell of slack: ISMs are rotated into the map grid
    near_end = cv2.dilate(end_cells, ring).astype(bool)
    occupied = p > 0.65
    assert occupied.sum() > 2000
    assert (occupied & near_end).sum() / occupied.sum() > 0.99
    occ_near = cv2.dilate((p > 0.5).astype(np.uint8), ring).astype(bool)
    assert occ_near[uv[:, 1], uv[:, 0]].mean() > 0.9
    # Corridors: the robot's own path between consecutive poses is free.
    poses = np.array([[s.pose.x, s.pose.y] for s in scans])
    path = np.vstack([a + np.linspace(0, 1, 10)[:, None] * (b - a)
                      for a, b in itertools.pairwise(poses)])
    puv = geom.world_to_index(path)
    assert (p[puv[:, 1], puv[:, 0]] < 0.3).mean() > 0.99


# -- CARMEN's field-of-view rules and ROBOTLASER1 ------------------------------------------
@pytest.mark.parametrize(("n", "first_deg", "step_deg", "fov_deg"), [
    (181, -90.0, 1.0, 180.0), (180, -90.0, 1.0, 179.0),
    (361, -90.0, 0.5, 180.0), (360, -90.0, 0.5, 179.5),
    (401, -50.0, 0.25, 100.0), (400, -50.0, 0.25, 99.75),
    (100, -90.0, 180.0 / 99, 180.0),
])
def test_fov_rules_of_carmen(n: int, first_deg: float, step_deg: float, fov_deg: float) -> None:
    a = np.degrees(carmen_angles(n).astype(np.float64))
    assert a.shape == (n,)
    assert a[0] == pytest.approx(first_deg, abs=1e-5)
    assert np.diff(a) == pytest.approx(step_deg, abs=1e-4)
    assert a[-1] - a[0] == pytest.approx(fov_deg, abs=1e-3)
    assert math.degrees(carmen_guess_fov(n)) == pytest.approx(fov_deg, abs=1e-9)
    # A 100-deg SICK setting looks straight ahead: symmetric about the x axis.
    if n == 401:
        assert a[200] == pytest.approx(0.0, abs=1e-5) and a[-1] == pytest.approx(50.0, abs=1e-4)


def robotlaser_line(ranges: list[float], *, start: float = -math.pi / 2,
                    res: float = math.pi / 180, max_range: float = 30.0,
                    laser: tuple[float, float, float] = (1.0, 2.0, 0.5),
                    robot: tuple[float, float, float] = (0.9, 2.0, 0.5),
                    remissions: tuple[float, ...] = (0.1, 0.2), stamp: float = 42.5) -> str:
    """A ROBOTLASER1 line in CARMEN 0.7's field order, written from the format itself."""
    fov = res * (len(ranges) - 1)
    words = ["ROBOTLASER1", "0", f"{start:.9f}", f"{fov:.9f}", f"{res:.9f}", f"{max_range}",
             "0.01", "0", str(len(ranges)), *(f"{r}" for r in ranges),
             str(len(remissions)), *(f"{r}" for r in remissions),
             *(f"{v}" for v in laser), *(f"{v}" for v in robot),
             "0.1", "0.0", "0.5", "0.3", "0.0", f"{stamp}", "host", f"{stamp + 0.01}"]
    return " ".join(words) + "\n"


def test_robotlaser1_line_carries_its_own_angles_range_and_poses() -> None:
    line = robotlaser_line([1.0, 2.0, 3.0], start=-math.pi / 4, res=math.pi / 4,
                           max_range=25.0, laser=(1.0, 2.0, math.pi / 2), robot=(0.8, 2.0, 1.5))
    scan = parse_robotlaser(line)
    assert scan.angles.tolist() == pytest.approx([-math.pi / 4, 0.0, math.pi / 4], abs=1e-7)
    assert scan.max_range == 25.0
    assert (scan.pose.x, scan.pose.y, scan.pose.yaw) == pytest.approx((1.0, 2.0, math.pi / 2))
    assert scan.odom_pose is not None and scan.odom_pose.x == pytest.approx(0.8)
    assert scan.stamp == 42.5
    # The beam ends, worked out by hand: the laser at (1, 2) looks along +y.
    ends = scan_endpoints_world(scan.ranges, scan.angles, scan.pose, scan.max_range)
    s = math.sqrt(0.5)
    np.testing.assert_allclose(ends, [[1.0 + s, 2.0 + s], [1.0, 4.0],
                                      [1.0 - 3 * s, 2.0 + 3 * s]], atol=1e-6)


@pytest.mark.parametrize("bad", [
    "ROBOTLASER1 0 -1.5 3.1 0.01 30 0.01 0\n",  # truncated header
    "ROBOTLASER1 0 -1.5 3.1 0.01 30 0.01 0 3 1.0 2.0\n",  # truncated readings
    robotlaser_line([1.0, 2.0]).replace(" 2 0.1 0.2 ", " 999 0.1 0.2 "),  # remission count
    robotlaser_line([1.0, 2.0], laser=(math.nan, 2.0, 0.0)),  # non-finite pose
    robotlaser_line([1.0, 2.0], res=0.0),  # no angular resolution
    robotlaser_line([1.0, 2.0, 3.0], res=4.0),  # more than one turn
    robotlaser_line([1.0, 2.0]).replace("ROBOTLASER1 0 ", "ROBOTLASER1 0 abc "),  # shifted
    "ROBOTLASER1 0 -1.5 3.1 0.01 30 0.01 0 -5\n",  # negative count
])
def test_malformed_robotlaser_lines_are_counted(tmp_path: Path, bad: str) -> None:
    path = tmp_path / "log"
    path.write_text(bad + robotlaser_line([1.0, 2.0, 3.0]))
    stats = CarmenStats()
    scans = list(read_carmen(path, stats=stats))
    assert len(scans) == 1 and scans[0].ranges.tolist() == [1.0, 2.0, 3.0]
    assert stats.malformed == 1 and stats.malformed_by_type == {"ROBOTLASER1": 1}


def test_robotlaser_only_log_and_every_line_type_counted(tmp_path: Path) -> None:
    lines = ["# CARMEN Logfile\n", "# file format is one message per line\n",
             "PARAM robot_front_laser_max 30.0 host 0\n",
             *(f"ODOM {i} 0 0 0 0 0 {i}.0 host {i}.0\n" for i in range(5)),
             "RAWLASER1 0 -1.57 3.14 0.0174 30 0.01 0 2 1.0 1.0 0 1.0 host 1.0\n",
             *(robotlaser_line([1.0 + i, 2.0, 3.0], stamp=float(i)) for i in range(3)),
             "ROBOTLASER2 " + robotlaser_line([1.0])[len("ROBOTLASER1 "):],  # rear laser
             "\n", "\x00\xff junk\n"]
    path = tmp_path / "robotlaser.log"
    path.write_bytes("".join(lines).encode("latin-1"))
    stats = CarmenStats()
    scans = list(read_carmen(path, stats=stats))
    assert [s.stamp for s in scans] == [0.0, 1.0, 2.0]
    assert stats.types == {"comment": 2, "PARAM": 1, "ODOM": 5, "RAWLASER1": 1,
                           "ROBOTLASER1": 3, "ROBOTLASER2": 1, "blank": 1, "other": 1}
    assert stats.scans_by_type == {"ROBOTLASER1": 3}
    assert stats.lines == len(lines) == stats.scans + stats.skipped + stats.malformed
    summary = stats.summary()
    assert summary.startswith(f"lines: {len(lines)} (ODOM 5, ROBOTLASER1 3, comment 2, ")
    assert "scans: 3 (ROBOTLASER1 3)" in summary and "0 malformed" in summary


def test_a_log_with_both_laser_kinds_is_read_once(tmp_path: Path) -> None:
    path = tmp_path / "both.log"
    path.write_text(GOOD + robotlaser_line([1.0, 2.0]) + GOOD + robotlaser_line([1.0, 2.0]))
    stats = CarmenStats()
    scans = list(read_carmen(path, stats=stats))
    assert len(scans) == 2 and all(s.ranges.shape == (4,) for s in scans)  # the FLASER ones
    assert stats.duplicate == 2 and stats.laser_type == "FLASER"


def test_line_type_names_cannot_grow_without_bound(tmp_path: Path) -> None:
    path = tmp_path / "hostile.log"
    path.write_text("".join(f"TYPE{i} 1 2 3\n" for i in range(5000)))
    stats = CarmenStats()
    assert list(read_carmen(path, stats=stats)) == []
    assert len(stats.types) <= 65 and sum(stats.types.values()) == 5000


@needs_intel
def test_intel_log_line_types() -> None:
    stats = CarmenStats()
    assert sum(1 for _ in read_carmen(INTEL_LOG, stats=stats)) == 910
    assert stats.types == {"FLASER": 910, "NEFF": 910, "ODOM": 14541, "PARAM": 2, "comment": 2}
    assert stats.skipped == 14541 + 910 + 2 + 2 and stats.malformed == 0
    # 180 beams: CARMEN's 179 deg, from -90 deg (the Intel log's FLASER convention).
    assert carmen_angles(180)[0] == pytest.approx(-math.pi / 2)


def room_ranges(x: float, y: float, angles: npt.NDArray[np.float64], half: float = 2.0
                ) -> list[float]:
    """Ray-cast from (x, y) at world ``angles`` to the walls of the square room |x|, |y| = half."""
    out = []
    for a in angles:
        c, s = math.cos(a), math.sin(a)
        ts = [(w - x) / c for w in (-half, half) if abs(c) > 1e-12] + \
             [(w - y) / s for w in (-half, half) if abs(s) > 1e-12]
        out.append(min(t for t in ts if t > 0))
    return out


@pytest.mark.parametrize("n", [401, 361, 181])
def test_flaser_beams_of_every_fov_rule_land_on_the_walls(tmp_path: Path, n: int) -> None:
    """A 100-deg / 401-beam scan read with CARMEN's rules lands on the room's walls; read from
    -90 deg (the old rule) it would be rotated by 40 deg and miss them."""
    x, y, yaw = 0.3, -0.4, 0.7
    start = -math.radians(50.0) if n == 401 else -math.pi / 2
    step = {401: math.pi / 720, 361: math.pi / 360, 181: math.pi / 180}[n]
    world = yaw + start + step * np.arange(n)
    ranges = room_ranges(x, y, world)
    line = f"FLASER {n} " + " ".join(f"{r:.4f}" for r in ranges) + \
        f" {x} {y} {yaw} {x} {y} {yaw} 1.0 host 1.0\n"
    path = tmp_path / "room.log"
    path.write_text(line)
    scan = next(read_carmen(path))
    ends = scan_endpoints_world(scan.ranges, scan.angles, scan.pose, scan.max_range)
    on_wall = np.isclose(np.abs(ends).max(axis=1), 2.0, atol=2e-3)
    assert on_wall.all()
    if n == 401:
        old = scan_endpoints_world(scan.ranges, -math.pi / 2 + step * np.arange(n), scan.pose,
                                   scan.max_range)
        assert np.isclose(np.abs(old).max(axis=1), 2.0, atol=2e-3).mean() < 0.2
