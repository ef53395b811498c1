"""CARMEN replay through a real (embedded) server: walls land on the log's beam endpoints."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from sogm_service.adapters.carmen import (
    read_carmen,
)
from sogm_service.adapters.laser import scan_endpoints_world
from sogm_service.apps.cli import main as cli_main
from sogm_service.apps.replay import replay_carmen
from sogm_service.core.geometry import GridGeometry, window_geometry
from sogm_service.sim.fleet import replay_scans
from tests.conftest import ServerProcess, wait_processed
from tests.helpers import INTEL_LOG, needs_intel
from tests.raycast_reference import compare, reference_map
from tests.unit.adapters.test_carmen import robotlaser_line, room_ranges
from tests.unit.adapters.test_laser_lattice import DEVICE_MAX, USABLE, meets_targets
from tests.unit.adapters.test_laser_lattice import RES as LATTICE_RES

pytestmark = pytest.mark.integration



@needs_intel
def test_replayed_map_has_its_occupied_cells_on_beam_endpoints() -> None:
    scans = list(read_carmen(INTEL_LOG, limit=150))
    result = replay_carmen(INTEL_LOG, limit=150)
    assert result.scans == 150 and result.isms_fused == 150
    g, p = result.geometry, result.probabilities
    # Every beam endpoint (within the ISM's usable 20 m) as a cell of the returned map.
    ends = np.concatenate([scan_endpoints_world(s.ranges, s.angles, s.pose, min(s.max_range, 20.0))
                           for s in scans])
    cells = g.world_to_index(ends)
    near_end = np.zeros(p.shape, bool)
    inside = (cells[:, 0] >= 0) & (cells[:, 0] < g.width) & (cells[:, 1] >= 0) & \
        (cells[:, 1] < g.height)
    for du in (-1, 0, 1):  # within one cell: ISMs are resampled from the sensor's frame
        for dv in (-1, 0, 1):
            u = np.clip(cells[inside, 0] + du, 0, g.width - 1)
            v = np.clip(cells[inside, 1] + dv, 0, g.height - 1)
            near_end[v, u] = True
    occupied = p > 0.65
    assert occupied.sum() > 1000
    assert (occupied & near_end).sum() / occupied.sum() > 0.99
    # The corridors the robot drove through are free.
    path = g.world_to_index(np.array([[s.pose.x, s.pose.y] for s in scans]))
    assert (p[path[:, 1], path[:, 0]] < 0.3).mean() > 0.99


@needs_intel
def test_replay_command_writes_the_png(tmp_path: Path) -> None:
    png = tmp_path / "intel.png"
    assert cli_main(["replay", "carmen", str(INTEL_LOG), "--limit", "40", "--png", str(png)]) == 0
    assert png.stat().st_size > 1000


# -- logs without usable scans, ROBOTLASER1-only logs, the line summary --------------------
@pytest.mark.parametrize("content", [
    "# ODOM only\n" + "ODOM 0 0 0 0 0 0 1.0 host 1.0\n" * 20,
    "",
    "FLASER 180 1.0\n" * 3,  # malformed only
])
def test_a_log_without_usable_scans_is_one_line_and_exit_2(
        tmp_path: Path, content: str, capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "empty.log"
    log.write_text(content)
    png = tmp_path / "out.png"
    assert cli_main(["replay", "carmen", str(log), "--png", str(png)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert "no usable laser scans" in err and "lines:" in err
    assert not png.exists()


def test_limit_zero_is_refused_before_anything_starts(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "one.log"
    log.write_text(robotlaser_line([1.0, 2.0, 3.0]))
    assert cli_main(["replay", "carmen", str(log), "--limit", "0",
                     "--png", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err
    assert "--limit is 0" in err and len(err.strip().splitlines()) == 1


def test_a_robotlaser1_log_replays_into_walls_where_they_are(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A square room (walls at |x|, |y| = 2 m) seen by ROBOTLASER1 lines whose laser pose and
    angles are their own: the map's walls are on the room's walls, its middle is free."""
    n = 181
    lines = ["# ROBOTLASER1 only\n", "PARAM robot_frontlaser_offset 0.1 host 0\n"]
    k = 0
    for x, y in ((0.0, 0.0), (0.8, -0.6), (-0.7, 0.9)):
        for yaw in (0.0, math.pi / 2, math.pi, -math.pi / 2):
            angles = yaw - math.pi / 2 + math.pi / 180 * np.arange(n)
            lines.append(f"ODOM {x} {y} {yaw} 0 0 0 {k}.0 host {k}.0\n")
            lines.append(robotlaser_line(room_ranges(x, y, angles), laser=(x, y, yaw),
                                         robot=(x - 0.1, y, yaw), stamp=float(k)))
            k += 1
    log = tmp_path / "room.log"
    log.write_text("".join(lines))
    npy = tmp_path / "room.npy"
    assert cli_main(["replay", "carmen", str(log), "--png", str(tmp_path / "room.png"),
                     "--npy", str(npy), "--resolution", "0.05"]) == 0
    out = capsys.readouterr().out
    assert f"replayed {k} scans" in out
    assert f"scans: {k} (ROBOTLASER1 {k})" in out and f"ODOM {k}" in out
    p = np.load(npy)
    scans = list(read_carmen(log))
    result_geometry = _replay_window(scans)
    centres = result_geometry.cell_centers().reshape((*p.shape, 2))
    d_wall = 2.0 - np.abs(centres).max(axis=2)  # > 0 inside the room
    occupied = p > 0.65
    assert occupied.sum() > 200
    assert (np.abs(d_wall[occupied]) <= 0.1).all()  # every occupied cell on a wall
    inside = d_wall > 0.2
    assert (p[inside] < 0.35).mean() > 0.95  # the room's floor is free


def _replay_window(scans: list) -> GridGeometry:  # type: ignore[type-arg]
    from sogm_service.apps.replay import _bounds_window
    from sogm_service.core.geometry import window_geometry

    w = _bounds_window(scans, 0.05)
    return window_geometry(w["x"], w["y"], w["yaw"], w["width"], w["height"], w["resolution"])


@needs_intel
def test_replay_into_a_running_server_through_a_zenoh_config_file(tmp_path: Path) -> None:
    """``--zenoh-config`` alone reaches the server: the file (not --connect) names where."""
    import json

    from sogm_service.client import MapClient
    from tests.conftest import start_server

    srv = start_server(tmp_path)
    try:
        config = tmp_path / "robot.json5"
        config.write_text(json.dumps({"mode": "client", "connect": {"endpoints": [srv.endpoint]},
                                      "scouting": {"multicast": {"enabled": False}}}))
        png = tmp_path / "intel.png"
        assert cli_main(["replay", "carmen", str(INTEL_LOG), "--limit", "20", "--zenoh-config",
                         str(config), "--png", str(png)]) == 0
        with MapClient.connect(srv.endpoint) as client:
            assert client.stats().counters.get("isms_fused") == 20
    finally:
        assert srv.terminate() == 0


@needs_intel
def test_replay_publishes_the_log_to_a_real_server(server: ServerProcess) -> None:
    scans = list(read_carmen(INTEL_LOG, limit=60))
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


@needs_intel
def test_replay_carmen_is_sharp_by_default() -> None:
    from sogm_service.apps.replay import replay_carmen

    scans = list(read_carmen(INTEL_LOG, limit=120))
    result = replay_carmen(INTEL_LOG, limit=120)
    g = result.geometry
    centres = g.cell_centers()
    cu = np.floor(centres[..., 0] / LATTICE_RES).astype(np.int64)
    cv = np.floor(centres[..., 1] / LATTICE_RES).astype(np.int64)
    box = (int(cu.min()), int(cv.min()), int(cu.max() - cu.min() + 1),
           int(cv.max() - cv.min() + 1))
    ref = reference_map([(s.pose.x, s.pose.y, s.pose.yaw, s.ranges, s.angles) for s in scans],
                        LATTICE_RES, USABLE, DEVICE_MAX, box)
    p = result.probabilities
    mapped = np.where(p > 0.5, 1, np.where(p < 0.5, -1, 0))
    # The reply's cell (r, c) is the map cell under its centre (nearest): put it there.
    on_box = np.zeros(ref.logodds.shape, dtype=np.int16)
    on_box[cv - box[1], cu - box[0]] = mapped
    c = compare(on_box, ref)
    print(f"replay carmen (120 scans): {c}")
    assert meets_targets(c), c
