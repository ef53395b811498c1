"""A server with a tile store and a memory budget gives its memory back once it evicted tiles:
after a burst of large ISMs, the process's RSS returns to the budget plus a fixed overhead.

The overhead stated by the performance page (docs/performance.md#memory-after-eviction): 250 MB
beyond the budget, for the interpreter and its libraries (~85 MB idle), the Zenoh session and
the temporaries the allocator keeps for reuse.
"""

from __future__ import annotations

import platform
from pathlib import Path

import pytest

from sogm_service.bench.compute import MAP_RES, synthetic_ism
from sogm_service.core.geometry import Pose2D
from tests.conftest import start_server, wait_processed, wait_until

pytestmark = [pytest.mark.integration,
              pytest.mark.skipif(platform.libc_ver()[0] != "glibc" or
                                 not Path("/proc/self/status").exists(),
                                 reason="RSS from /proc; the allocator's trim is glibc's")]

BUDGET_MB = 64
OVERHEAD_MB = 250


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return float(line.split()[1]) / 1024
    raise RuntimeError(f"no VmRSS for pid {pid}")


def test_rss_returns_to_the_budget_after_a_burst(tmp_path: Path) -> None:
    srv = start_server(tmp_path, {
        "map": {"resolution": MAP_RES},
        "storage": {"directory": str(tmp_path / "store"), "memory_budget_mb": BUDGET_MB,
                    "checkpoint_interval_s": 1.0}})
    try:
        with srv.client() as client:
            n = 0
            for layer in range(4):  # 4 layers over 200 m x 200 m: 40 MB a layer, 160 MB
                for i in range(4):
                    for j in range(4):
                        client.publish_ism(f"ism/robot1/layer{layer}", synthetic_ism(1000, n),
                                           resolution=MAP_RES,
                                           origin=Pose2D(i * 50.0, j * 50.0, 0.0))
                        n += 1
            counters = wait_processed(client, n, 120.0)
            assert counters.get("isms_fused", 0) == n, counters
            peak = _rss_mb(srv.proc.pid)

            def given_back() -> bool:
                s = client.stats()
                return (s.extra.get("writes_pending") == 0
                        and s.counters.get("memory_given_back", 0) >= 1
                        and s.extra["resident_mb"] <= BUDGET_MB)

            assert wait_until(given_back, 30.0, 0.2), client.stats()
            stats = client.stats()
            rss = _rss_mb(srv.proc.pid)
        assert stats.counters.get("tiles_evicted", 0) > 0
        assert stats.extra["tiles_written_total"] > 0 and stats.extra["write_errors"] == 0
        assert rss <= BUDGET_MB + OVERHEAD_MB, (
            f"RSS {rss:.0f} MB after eviction (peak {peak:.0f} MB), budget {BUDGET_MB} MB")
    finally:
        srv.terminate()
