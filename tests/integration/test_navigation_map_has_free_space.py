"""Two robots write their own layers (``ism/robot1/...``, ``ism/robot2/...``) of areas that do
not overlap, each free space with a wall.  Every navigation map of a real server, the fused
query with ``method=max``, ``export nav2``, the ROS 2 ``map`` topic and the ``GetMap`` service,
shows both areas free, both walls occupied and the gap between them unknown: in max pooling a
layer without evidence in a cell has no opinion there.

And stamps: ``publish-ism`` stamps now by default, takes ``--stamp SECONDS``, and an ISM so old
that its forgetting layer would keep nothing of it is refused with ``stale_stamp`` (exit 2, a
counter in stats), never reported as fused.  The ROS 2 side is built from the message
definitions with rosbags; nothing there uses the project's encoders.
"""

from __future__ import annotations

import struct
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("rosbags")  # the [ros2] extra
yaml = pytest.importorskip("yaml")
pytest.importorskip("xxhash")

import zenoh  # noqa: E402
import zenoh.ext  # noqa: E402

from sogm_service.client import MapClient, Pose2D  # noqa: E402
from sogm_service.client.session import loopback_settings, open_session  # noqa: E402
from tests.conftest import ServerProcess, start_server, wait_until  # noqa: E402
from tests.integration.test_first_contact import one_line_error, run_cli  # noqa: E402
from tests.integration.test_ros2_bridge import (  # noqa: E402
    GETMAP_H,
    GETMAP_T,
    GRID_T,
    TS,
    T,
    spec_gid,
    tokens,
)
from tests.unit.adapters.test_nav2 import map_server_trinary, read_pgm  # noqa: E402

pytestmark = pytest.mark.integration

MAP = "fleet"
RES = 0.05
TIMEOUT = 5.0
SIDE = 40  # cells of each robot's square ISM (2 m)
AREAS = {"robot1": 0.0, "robot2": 3.0}  # x of each ISM's origin: a 1 m gap between them


def robot_cells(robot: str) -> np.ndarray:
    """nav_msgs occupancy of a robot's ISM: free, with a wall (a column for robot1, a row for
    robot2)."""
    cells = np.zeros((SIDE, SIDE), np.int8)
    if robot == "robot1":
        cells[:, 30] = 100
    else:
        cells[10, :] = 100
    return cells


def block(grid: np.ndarray, ox: float, oy: float, x0: float, y0: float, w: int,
          h: int) -> np.ndarray:
    """The ``h x w`` cells of ``grid`` (row 0 at the smallest y, origin ``(ox, oy)``) whose
    cell (0, 0) has its corner at ``(x0, y0)``."""
    u, v = round((x0 - ox) / RES), round((y0 - oy) / RES)
    assert u >= 0 and v >= 0 and v + h <= grid.shape[0] and u + w <= grid.shape[1]
    return grid[v:v + h, u:u + w]


def check_navigation_map(grid: np.ndarray, ox: float, oy: float, what: str) -> None:
    """Both robots' areas as their ISMs say (free 0, wall 100) and the gap unknown (-1)."""
    for robot, x0 in AREAS.items():
        got = block(grid, ox, oy, x0, 0.0, SIDE, SIDE)
        want = robot_cells(robot)
        assert np.array_equal(got, want), (
            f"{what}, {robot}: {np.count_nonzero(got == 0)} free (want "
            f"{np.count_nonzero(want == 0)}), {np.count_nonzero(got == 100)} occupied (want "
            f"{np.count_nonzero(want == 100)}), {np.count_nonzero(got == -1)} unknown")
    gap = block(grid, ox, oy, 2.0, 0.0, 20, SIDE)
    assert (gap == -1).all(), f"{what}: the gap has {np.count_nonzero(gap != -1)} known cells"


def trinary(values: np.ndarray) -> np.ndarray:
    """Occupancy 0..100 / -1 as nav2's trinary cells at its default thresholds."""
    out = np.full(values.shape, -1, np.int8)
    out[(values >= 0) & (values <= 25)] = 0
    out[values >= 65] = 100
    return out


@pytest.fixture
def fleet_server(tmp_path: Path) -> Any:
    srv = start_server(tmp_path, {"map": {"name": MAP, "resolution": RES,
                                          "forget": {"*/people": 5.0}},
                                  "ros2": {"enabled": True, "publish_period_s": 0.2,
                                           "region": "known"}})
    try:
        with MapClient.connect(srv.endpoint, map_name=MAP) as client:
            for robot, x0 in AREAS.items():
                client.publish_ism(f"ism/{robot}/laser/obstacle", robot_cells(robot),
                                   resolution=RES, origin=Pose2D(x0, 0.0, 0.0), wait=True)
        yield srv
    finally:
        assert srv.terminate() == 0


def test_fused_max_and_export_nav2_show_both_robots_free_space(fleet_server: ServerProcess,
                                                               tmp_path: Path) -> None:
    with MapClient.connect(fleet_server.endpoint, map_name=MAP) as client:
        fused = client.fused(method="max", x=2.5, y=1.0, width=5.0, height=2.0,
                             interp="nearest", encoding="occupancy_i8")
        assert fused.layers == ["robot1/laser/obstacle", "robot2/laser/obstacle"]
        g = fused.geometry
        check_navigation_map(np.asarray(fused.data), g.origin.x, g.origin.y, "fused max")
    out = tmp_path / "nav2"
    run = run_cli("export", "nav2", "--out", str(out), "--connect", fleet_server.endpoint,
                  "--map", MAP, "--box", "0", "0", "5", "2")  # --method max is the default
    assert run.returncode == 0, run.stderr
    free = sum(int(np.count_nonzero(robot_cells(r) == 0)) for r in AREAS)
    occupied = sum(int(np.count_nonzero(robot_cells(r) == 100)) for r in AREAS)
    assert f"{free} free, {occupied} occupied, {100 * 40 - free - occupied} unknown" \
        in run.stdout, run.stdout
    assert "warning" not in run.stderr
    doc = yaml.safe_load((out / "map.yaml").read_text())
    cells = np.flipud(map_server_trinary(read_pgm(out / doc["image"]), doc["occupied_thresh"],
                                         doc["free_thresh"], doc["negate"]))
    check_navigation_map(cells, doc["origin"][0], doc["origin"][1], "export nav2")


def _decode_grid(payload: bytes) -> tuple[np.ndarray, float, float]:
    m = TS.deserialize_cdr(payload, "nav_msgs/msg/OccupancyGrid")
    assert m.info.resolution == pytest.approx(RES) and m.header.frame_id == "map"
    cells = np.asarray(m.data, np.int8).reshape(m.info.height, m.info.width)
    return cells, m.info.origin.position.x, m.info.origin.position.y


def test_ros2_map_topic_and_get_map_show_both_robots_free_space(
        fleet_server: ServerProcess) -> None:
    ros = open_session(loopback_settings(connect=fleet_server.endpoint))
    maps: list[bytes] = []
    # transient local, as rmw_zenoh subscribes to the map: the last grid published, then each
    sub = zenoh.ext.declare_advanced_subscriber(
        ros, f"0/sogm/{MAP}/map/{GRID_T}/*", lambda s: maps.append(s.payload.to_bytes()),
        history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=1))
    free = sum(int(np.count_nonzero(robot_cells(r) == 0)) for r in AREAS)
    try:
        assert wait_until(lambda: any("/SS/%/%/sogm_service/" in t for t in tokens(ros)),
                          TIMEOUT)
        # a grid published after both ISMs were fused (the server publishes every 0.2 s)
        assert wait_until(lambda: bool(maps) and np.count_nonzero(
            _decode_grid(maps[-1])[0] == 0) >= free, TIMEOUT), \
            f"{len(maps)} maps, the last with too few free cells"
        cells, ox, oy = _decode_grid(maps[-1])
        check_navigation_map(cells, ox, oy, "ROS 2 map topic")
        assert np.array_equal(trinary(cells), cells)  # nothing between free and occupied

        client_token = (f"@ros2_lv/0/abc/0/41/SC/%/%/nav2_client/%sogm%{MAP}%get_map/"
                        f"{GETMAP_T}/{GETMAP_H}/::,10:,:,:,,")
        request = bytes(TS.serialize_cdr(T["nav_msgs/srv/GetMap_Request"](
            structure_needs_at_least_one_member=0), "nav_msgs/srv/GetMap_Request"))
        attachment = struct.pack("<qqB", 1, time.time_ns(), 16) + spec_gid(client_token)
        replies = list(ros.get(f"0/sogm/{MAP}/get_map/{GETMAP_T}/{GETMAP_H}",
                               payload=request, attachment=attachment,
                               target=zenoh.QueryTarget.ALL_COMPLETE, timeout=TIMEOUT))
        assert len(replies) == 1 and replies[0].ok is not None
        resp = TS.deserialize_cdr(replies[0].ok.payload.to_bytes(),
                                  "nav_msgs/srv/GetMap_Response")
        info = resp.map.info
        got = np.asarray(resp.map.data, np.int8).reshape(info.height, info.width)
        check_navigation_map(got, info.origin.position.x, info.origin.position.y, "GetMap")
    finally:
        sub.undeclare()
        ros.close()


def test_publish_ism_stamps_now_and_refuses_an_ism_its_layer_would_forget(
        fleet_server: ServerProcess, tmp_path: Path) -> None:
    grid = tmp_path / "person.npy"
    np.save(grid, np.full((10, 10), 100, np.int8))
    args = ["publish-ism", str(grid), "--connect", fleet_server.endpoint, "--map", MAP,
            "--key", "ism/robot1/camera/people", "--resolution", str(RES), "--x", "6"]
    before = time.time()
    ok = run_cli(*args)
    assert ok.returncode == 0, ok.stderr
    assert ok.stdout.startswith("fused 10x10 occupancy_i8 ISM on ism/robot1/camera/people")
    stamp = float(ok.stdout.rsplit("stamp ", 1)[1].rstrip(")\n"))
    assert before - 1 <= stamp <= time.time()  # default: now
    # 0.0, the stamp publish-ism used to send: a 5 s half-life keeps nothing of it
    stale = run_cli(*args, "--x", "7", "--stamp", "0")
    line = one_line_error(stale)
    assert "[stale_stamp]" in line and "(half-life 5 s)" in line, line
    assert line.endswith("(stamps: Unix time in s)"), line  # the whole reason
    # two half-lives old: fused, at a quarter of its weight
    aged = run_cli(*args, "--x", "8", "--stamp", repr(stamp - 10.0))
    assert aged.returncode == 0, aged.stderr
    bad = one_line_error(run_cli(*args, "--stamp", "nan"))
    assert "--stamp must be a finite number" in bad
    with MapClient.connect(fleet_server.endpoint, map_name=MAP) as client:
        assert client.stats().rejected.get("stale_stamp") == 1
        sub = client.submap(x=7.25, y=0.25, width=2.5, height=0.5,
                            layers=["robot1/camera/people"], interp="nearest",
                            encoding="logodds_i16")
        cells = np.asarray(sub.data)[0]
        first, refused, quarter = cells[:, 0:10], cells[:, 20:30], cells[:, 40:50]
    hi = round(1000 * np.log(0.999 / 0.001))  # occupied 100 % at the default clamp
    assert (first > hi * 0.9).all()  # read at the map's clock: just now
    assert not refused.any()  # the refused ISM changed nothing
    assert (np.abs(quarter - hi / 4) <= hi * 0.02).all()
    log = fleet_server.log()
    assert log.count("rejected ISM [stale_stamp]") == 1
