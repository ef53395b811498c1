"""The machinery of the ``cluster_scale`` bench row: its workload, its CPU caps and its cost
fit (never a speed: that is the bench's to measure)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from sogm_service.bench import cgroups, cluster_scale
from sogm_service.core.geometry import TileLattice
from sogm_service.service.server.pipeline import ism_geometry
from sogm_service.wire import codec
from sogm_service.wire.messages import IsmMessage


def test_every_ism_lies_in_one_tile_and_every_tile_gets_one() -> None:
    lattice = TileLattice(cluster_scale.RES, 256)
    tiles = []
    for payload in cluster_scale.payloads():
        assert codec.unpack(payload)["compression"] == "zstd"  # as MapClient sends ISMs
        msg = codec.decode(IsmMessage, payload)
        touched = lattice.tiles_overlapping(ism_geometry(msg))
        assert len(touched) == 1, (msg.origin, touched)
        tiles.append(touched[0])
    n = cluster_scale.TILES
    assert sorted(tiles) == [(i, j) for i in range(n) for j in range(n)]
    # consecutive ISMs land far apart, so any window of them spreads over the members
    assert tiles[0] != tiles[1] and abs(tiles[0][1] - tiles[1][1]) > 1


def test_costs_recover_what_fused_and_checked_isms_cost() -> None:
    rng = np.random.default_rng(0)
    samples = []
    for _ in range(6):
        fused, checked = (int(v) for v in rng.integers(100, 3000, 2))
        samples.append((fused, checked, fused * 400e-6 + checked * 50e-6))
    got_fused, got_checked = cluster_scale.costs(samples)
    assert got_fused == pytest.approx(400e-6) and got_checked == pytest.approx(50e-6)


def test_caps_hold_a_process_under_its_quota_and_are_removed() -> None:
    kind, root = cgroups._controller()
    if root is None:
        pytest.skip("no writable cgroup CPU controller on this machine")
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        with cgroups.cpu_caps(0.3) as caps:
            caps.place("member0", child.pid)
            assert caps.base is not None
            group = caps.base / "member0"
            assert str(child.pid) in (group / "cgroup.procs").read_text().split()
            if kind == "v2":
                assert (group / "cpu.max").read_text().split() == [
                    str(int(0.3 * cgroups.PERIOD_US)), str(cgroups.PERIOD_US)]
            else:
                assert int((group / "cpu.cfs_quota_us").read_text()) == \
                    int(0.3 * cgroups.PERIOD_US)
            assert "0.3 CPU per member" in caps.describe()
            made = [caps.base, *([caps.acct] if caps.acct is not None else [])]
        for base in made:  # removed, the child moved back to the hierarchy's root first
            assert not base.exists(), base
        assert child.poll() is None
    finally:
        child.kill()
        child.wait(5)
