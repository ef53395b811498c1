"""CARMEN log reader and an offline map of the Intel Research Lab log."""

from __future__ import annotations

import gzip
import itertools
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from sogm_service.adapters.carmen import CarmenStats, carmen_angles, parse_flaser, read_carmen
from sogm_service.adapters.laser import scan_endpoints_world
from sogm_service.core.geometry import window_geometry
from sogm_service.sim.fleet import replay_scans
from sogm_service.sim.offline import map_scans
from tests.conftest import ServerProcess, wait_processed

INTEL = Path("/work/shared/data/carmen/intel-corrected.log.gz")
needs_intel = pytest.mark.skipif(not INTEL.exists(), reason="Intel log not available")

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
    scans = list(read_carmen(INTEL, stats=stats))
    assert len(scans) == 910 and stats.malformed == 0
    first = scans[0]
    assert first.ranges.shape == (180,) and first.ranges.dtype == np.float32
    assert (first.pose.x, first.pose.y, first.pose.yaw) == pytest.approx(
        (0.600266, -0.0320327, -0.354665))
    assert first.stamp == pytest.approx(32.9068)
    # The log's own stamps step back a little four times; the reader keeps them as they are.
    assert scans[-1].stamp - scans[0].stamp > 2000
    assert len(list(read_carmen(INTEL, limit=7))) == 7


@needs_intel
def test_intel_slice_map_occupied_on_endpoints_and_corridors_free() -> None:
    scans = list(read_carmen(INTEL, limit=250))[100:250]
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


@needs_intel
@pytest.mark.integration
def test_replay_publishes_the_log_to_a_real_server(server: ServerProcess) -> None:
    scans = list(read_carmen(INTEL, limit=60))
    stats = replay_scans(scans, server.endpoint, robot="intel", speed=0.0)
    assert stats.isms == 60 and stats.poses == 60
    with server.client() as client:
        counters = wait_processed(client, stats.isms)
        assert counters.get("isms_fused", 0) == 60, counters
        assert client.info().layers == ["obstacle"]
        win = client.submap(x=0.0, y=0.0, width=12.0, height=12.0, layers=["obstacle"])
    p = win.probabilities()[0]
    geom = window_geometry(0.0, 0.0, 0.0, 12.0, 12.0, 0.05)
    ends = np.vstack([scan_endpoints_world(s.ranges, s.angles, s.pose, 20.0) for s in scans])
    uv = geom.world_to_index(ends)
    keep = (uv[:, 0] >= 0) & (uv[:, 0] < geom.width) & (uv[:, 1] >= 0) & (uv[:, 1] < geom.height)
    end_cells = np.zeros(geom.shape, np.uint8)
    end_cells[uv[keep, 1], uv[keep, 0]] = 1
    near_end = cv2.dilate(end_cells, np.ones((3, 3), np.uint8)).astype(bool)
    occupied = p > 0.65
    assert occupied.sum() > 300
    assert (occupied & near_end).sum() / occupied.sum() > 0.99
    start = geom.world_to_index(np.array([scans[0].pose.x, scans[0].pose.y]))
    assert p[start[1], start[0]] < 0.3
