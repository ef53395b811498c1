"""A ROS bag replayed into a real (embedded) server, and nav2 map files exported from one
server and imported into another."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")  # the [ros2] extra
yaml = pytest.importorskip("yaml")

from tests.unit.adapters.test_nav2 import map_server_trinary, read_pgm  # noqa: E402
from tests.unit.adapters.test_rosbag import write_bag  # noqa: E402

pytestmark = pytest.mark.integration


def test_replay_rosbag_fuses_the_scan_and_the_grid(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    from sogm_service.apps import replay

    bag = tmp_path / "b"
    write_bag(bag, ros1=False)
    png = tmp_path / "bag.png"
    assert replay.main(["rosbag", str(bag), "--png", str(png)]) == 0
    out = capsys.readouterr().out
    assert "replayed 2 scans" in out and "2 ISMs fused" in out  # 1 localised scan + 1 grid
    assert "unlocalized scans 1" in out and png.stat().st_size > 0


def test_export_then_import_nav2_through_real_servers(tmp_path: Path) -> None:
    """``export nav2`` of a served map, read back as map_server does; ``import nav2`` of it
    into a second server gives the same trinary cells."""
    from sogm_service.apps import nav2tool
    from sogm_service.client import MapClient, Pose2D
    from tests.conftest import start_server, wait_processed

    cells = np.zeros((40, 60), np.int8)
    cells[10:30, 20:40] = 100
    cells[:, :5] = -1
    first = start_server(tmp_path, name="first")
    second = start_server(tmp_path, name="second")
    try:
        with MapClient.connect(first.endpoint) as client:
            client.publish_ism("ism/mapper/laser/walls", cells, resolution=0.05,
                               origin=Pose2D(0.0, 0.0, 0.0))
            wait_processed(client, 1)
        out = tmp_path / "nav2"
        assert nav2tool.export_main(["nav2", "--out", str(out), "--connect", first.endpoint,
                                     "--box", "0", "0", "3", "2"]) == 0
        doc = yaml.safe_load((out / "map.yaml").read_text())
        assert doc["resolution"] == 0.05 and doc["origin"][:2] == [0.0, 0.0]
        px = read_pgm(out / doc["image"])
        trinary = np.flipud(map_server_trinary(px, doc["occupied_thresh"], doc["free_thresh"],
                                                doc["negate"]))  # image top = largest y
        want = np.where(cells == 100, 100, np.where(cells == 0, 0, -1)).astype(np.int8)
        assert np.array_equal(trinary, want)
        assert nav2tool.import_main(["nav2", str(out / "map.yaml"), "--layer", "prior/walls",
                                     "--connect", second.endpoint]) == 0
        with MapClient.connect(second.endpoint) as client:
            wait_processed(client, 1)
            got = client.submap(x=1.5, y=1.0, width=3.0, height=2.0, resolution=0.05,
                                layers=["prior/walls"], interp="nearest")
        p = got.probabilities()[0]
        assert np.array_equal(np.where(p > 0.6, 100, np.where(p < 0.4, 0, -1)), want)
    finally:
        assert first.terminate() == 0 and second.terminate() == 0
