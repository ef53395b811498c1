"""A ROS 2 map appears as soon as an ISM is fused, with no robot pose anywhere: the default
publish region (``recent``) covers what is known around the ISMs fused lately.  A real
``serve --ros2``, an ISM from the real ``publish-ism`` CLI (it sends no pose), a ROS subscriber
built from the message definitions (rosbags)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")  # the [ros2] extra
pytest.importorskip("xxhash")

from sogm_service.client.session import loopback_settings, open_session
from tests.conftest import start_server, wait_until
from tests.integration.test_ros2_bridge import GRID_H, GRID_T
from tests.integration.test_ros2_map_updates import Holder

pytestmark = pytest.mark.integration

MAP = "noposes"
TIMEOUT = 15.0


def test_one_publish_ism_without_a_pose_makes_the_map_topic(tmp_path: Path) -> None:
    srv = start_server(tmp_path, {"map": {"name": MAP, "resolution": 0.05, "tile_size": 256},
                                  "ros2": {"enabled": True, "publish_period_s": 0.2}})
    ros = open_session(loopback_settings(connect=srv.endpoint))
    fused = Holder()
    sub = ros.declare_subscriber(f"0/sogm/{MAP}/map/{GRID_T}/{GRID_H}", fused.on_grid)
    try:
        scan = np.full((30, 40), 20, np.uint8)  # 40 x 30 cells of free space
        scan[:, -2:] = 240  # a wall along its east side
        np.save(tmp_path / "scan.npy", scan)
        cli = subprocess.run(
            [sys.executable, "-m", "sogm_service", "publish-ism", str(tmp_path / "scan.npy"),
             "--connect", srv.endpoint, "--map", MAP, "--key", "ism/robot1/laser/obstacle",
             "--resolution", "0.05", "--x", "3.0", "--y", "2.0"],
            capture_output=True, text=True, timeout=60)
        assert cli.returncode == 0, cli.stderr
        assert wait_until(lambda: fused.grid is not None, TIMEOUT), srv.log()
        g = fused.grid
        cells = fused.cells()
        assert cells is not None
        # the grid holds the ISM's cells (and little else: its extent is the known box,
        # rounded out), on the map's lattice
        assert g.info.resolution == pytest.approx(0.05)
        assert g.info.width * g.info.height <= 4 * 40 * 30 + 64 * 64
        assert np.count_nonzero(cells >= 0) == 40 * 30
        assert np.count_nonzero(cells >= 65) == 2 * 30  # the wall
        assert np.count_nonzero((cells >= 0) & (cells < 35)) == 38 * 30  # the free space
        x0, y0 = g.info.origin.position.x, g.info.origin.position.y
        assert x0 <= 3.0 and y0 <= 2.0  # (x, y) is the corner of the ISM's cell (0, 0)
        assert x0 + g.info.width * 0.05 >= 5.0 and y0 + g.info.height * 0.05 >= 3.5
    finally:
        sub.undeclare()
        ros.close()
        assert srv.terminate() == 0
    log = srv.log()
    assert f"advertising /sogm/{MAP}/map (" in log, log  # one line when a topic first appears
    assert log.count(f"advertising /sogm/{MAP}/map (") == 1
