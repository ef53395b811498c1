"""CARMEN replay through a real (embedded) server: walls land on the log's beam endpoints."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sogm_service.adapters.carmen import read_carmen
from sogm_service.adapters.laser import scan_endpoints_world
from sogm_service.apps.cli import main as cli_main
from sogm_service.apps.replay import replay_carmen

pytestmark = pytest.mark.integration

# The repository is checked out with shared/ beside it (here and in CI).
LOG = Path(__file__).resolve().parents[2] / "shared/data/carmen/intel-corrected.log.gz"


@pytest.mark.skipif(not LOG.exists(), reason="shared/data/carmen not beside the checkout")
def test_replayed_map_has_its_occupied_cells_on_beam_endpoints() -> None:
    scans = list(read_carmen(LOG, limit=150))
    result = replay_carmen(LOG, limit=150)
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


@pytest.mark.skipif(not LOG.exists(), reason="shared/data/carmen not beside the checkout")
def test_replay_command_writes_the_png(tmp_path: Path) -> None:
    png = tmp_path / "intel.png"
    assert cli_main(["replay", "carmen", str(LOG), "--limit", "40", "--png", str(png)]) == 0
    assert png.stat().st_size > 1000
