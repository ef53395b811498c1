"""A simulated fleet publishes to a real server: every ISM fused, the served map as the world."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from sogm_service.core.geometry import window_geometry
from sogm_service.sim.fleet import run_fleet
from sogm_service.sim.robots import simulate
from sogm_service.sim.sensors import lookup
from sogm_service.sim.worlds import World
from tests.conftest import ServerProcess, wait_processed
from tests.unit.sim import test_sensors as sim

pytestmark = pytest.mark.integration

warehouse = sim.warehouse  # the module's world fixture, shared with the simulator's tests


def test_fleet_publishes_to_a_real_server(server: ServerProcess, warehouse: World) -> None:
    stats = run_fleet(warehouse, server.endpoint, robots=2, duration_s=3.0, rate_hz=2.0,
                      seed=1, realtime=False)
    assert stats.steps == 14 and stats.poses == 14
    assert stats.isms == 14 * 4  # laser obstacle + camera floor, shelf, pallet
    with server.client() as client:
        counters = wait_processed(client, stats.isms)
        assert counters.get("isms_fused", 0) == stats.isms, counters
        info = client.info()
        assert sorted(info.layers) == ["floor", "obstacle", "pallet", "shelf"]
        # The served obstacle layer agrees with the offline map of the same run.
        start = next(iter(simulate(warehouse, 2, 3.0, 2.0, seed=1, sensors=[]))).true_pose
        win = client.submap(x=start.x, y=start.y, width=8.0, height=8.0, layers=["obstacle"],
                            interp="nearest")
    p = win.probabilities()[0]
    seen = p != 0.5
    assert seen.mean() > 0.3
    centres = window_geometry(start.x, start.y, 0.0, 8.0, 8.0, 0.05).cell_centers()
    truth, inside = lookup(warehouse, centres, warehouse.occupied)
    near = cv2.dilate(truth.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    occ = seen & (p > 0.5) & inside
    assert occ.sum() > 20
    assert near[occ].mean() > 0.95  # served hits are on real objects
