"""A real server forgets by the ISMs' stamps, and across a restart from its store."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from sogm_service.core.geometry import Pose2D
from tests.unit.core.map.test_forget import H

pytestmark = pytest.mark.integration


def test_server_forgets_by_stamps_and_across_a_restart(tmp_path: Path) -> None:
    from sogm_service.client.mapclient import MapClient
    from tests.conftest import start_server, wait_processed

    sections = {"map": {"resolution": 0.5, "tile_size": 16, "forget": {"*/people": H}},
                "storage": {"directory": str(tmp_path / "tiles")}}
    occ = np.full((1, 1), 80, dtype=np.int8)  # occupancy_i8 80 -> logit(0.8) = 1386
    l_occ = round(1000 * math.log(0.8 / 0.2))
    window = dict(x=2.0, y=2.0, width=4.0, height=4.0, resolution=0.5, interp="nearest",
                  encoding="logodds_i16", layers=["robot1/people", "robot1/walls"])

    def send(client: MapClient, layer: str, x: float, stamp: float) -> None:
        client.publish_ism(f"ism/robot1/{layer}", occ, resolution=0.5,
                           origin=Pose2D(x, 0.0, 0.0), encoding="occupancy_i8", stamp=stamp,
                           robot="robot1")

    server = start_server(tmp_path, sections)
    try:
        with MapClient.connect(server.endpoint, timeout=5.0) as client:
            send(client, "people", 0.0, 1000.0)
            send(client, "walls", 0.0, 1000.0)
            wait_processed(client, 2)
            send(client, "walls", 1.0, 1010.0)  # the map's clock moves to 1010
            wait_processed(client, 3)
            sub = client.submap(**window).data  # type: ignore[arg-type]
            assert sub[0, 0, 0] == math.trunc(l_occ * 0.5) == 693  # one half-life
            assert sub[1, 0, 0] == l_occ  # walls never forget
    finally:
        assert server.terminate() == 0  # flushes the tiles
    again = start_server(tmp_path, sections, name="again")
    try:
        with MapClient.connect(again.endpoint, timeout=5.0) as client:
            sub = client.submap(**window).data  # type: ignore[arg-type]
            assert sub[0, 0, 0] == 693  # read at the stored clock, decayed from its stamp
            send(client, "people", 3.0, 1020.0)  # decays the tile's layer from 1000 in place
            wait_processed(client, 1)
            sub = client.submap(**window).data  # type: ignore[arg-type]
            assert sub[0, 0, 0] == math.trunc(l_occ * 0.25) == 346
            assert sub[0, 0, 6] == l_occ
    finally:
        assert again.terminate() == 0
