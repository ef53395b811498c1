"""Queries to a real server are answered during an ingestion burst, before it ends."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from sogm_service.wire import codec
from sogm_service.wire.messages import IsmMessage, PoseModel
from tests.conftest import start_server, wait_processed

pytestmark = pytest.mark.integration


def _burst(n: int) -> list[bytes]:
    rng = np.random.default_rng(3)
    grid = rng.integers(0, 256, size=(256, 256), dtype=np.uint8)
    return [codec.encode(IsmMessage(
        resolution=0.075, origin=PoseModel(x=float(k % 7), y=float(k % 5), yaw=0.3 + k * 1e-3),
        width=256, height=256, encoding="prob_u8", data=grid.tobytes())) for k in range(n)]


def test_queries_during_an_ingestion_burst_are_answered_before_it_ends(tmp_path: Path) -> None:
    """Event order, not a time threshold: each query's reply comes back while the server has
    still not fused the whole burst, and no ISM of the burst is lost."""
    n = 1500
    payloads = _burst(n)
    srv = start_server(tmp_path)
    try:
        with srv.client(timeout=30.0) as robot, srv.client(timeout=30.0) as viewer:
            publisher = threading.Thread(
                target=lambda: [robot.publish_raw("ism/robot1/laser/obstacle", p)
                                for p in payloads])
            publisher.start()
            answered_during = 0
            while answered_during < 5:
                viewer.submap(x=3.0, y=2.0, yaw=0.3, width=12.8, height=12.8, resolution=0.05)
                fused = viewer.stats().counters.get("isms_fused", 0)
                if fused >= n:
                    break
                if fused > 0:
                    answered_during += 1
            publisher.join()
            counters = wait_processed(viewer, n, timeout=120.0)
        assert answered_during == 5, "the burst ended before five queries were answered"
        assert counters.get("isms_fused") == n and counters.get("isms_rejected", 0) == 0
        assert srv.terminate() == 0
    finally:
        if srv.proc.poll() is None:
            srv.terminate()
