"""Scan matching inside the server, over real Zenoh sessions (paper section III-C.2)."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sogm_service.bench.matching import synthetic_floorplan
from sogm_service.client.mapclient import MapClient
from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice
from sogm_service.core.map.tiles import TiledMap
from sogm_service.wire import codec
from sogm_service.wire.messages import MatchReport
from tests.conftest import start_server, wait_processed, wait_until

pytestmark = pytest.mark.integration

RES = 0.05
PLAN = synthetic_floorplan(512, seed=4)
TRUE = Pose2D(150 * RES, 150 * RES, 0.0)  # where the cut below really lies
CLAIMED = Pose2D(TRUE.x + 0.3, TRUE.y - 0.2, math.radians(4.0))  # drifted odometry


def _prob(l: np.ndarray) -> np.ndarray:
    return logodds.fixed_to_prob(l).astype(np.float32)


def _matching_server(tmp_path: Path, mode: str, on_failure: str = "fuse") -> object:
    return start_server(tmp_path, ism=[{"key_expr": "ism/**", "matching": {
        "mode": mode, "on_failure": on_failure, "layer": "obstacle"}}])


def _reports(client: MapClient) -> list[MatchReport]:
    got: list[MatchReport] = []
    client.session.declare_subscriber(
        client.key("matching", "**"),
        lambda s: got.append(codec.decode(MatchReport, s.payload.to_bytes())))
    time.sleep(0.3)
    return got


def _publish_reference_and_cut(client: MapClient) -> None:
    client.publish_ism("ism/mapper/laser/obstacle", _prob(PLAN), resolution=RES,
                       layer="obstacle")
    client.publish_ism("ism/robot1/laser/obstacle", _prob(PLAN[150:406, 150:406]),
                       resolution=RES, origin=CLAIMED, layer="obstacle", robot="robot1")


def _run_reference_and_cut(tmp_path: Path, mode: str) -> tuple[list[MatchReport], Any, Any]:
    """A server in ``mode``; the reference map, then the drifted cut: reports, stats, map."""
    srv = _matching_server(tmp_path, mode)
    try:
        with srv.client() as client:
            reports = _reports(client)
            _publish_reference_and_cut(client)
            wait_processed(client, 2)
            assert wait_until(lambda: len(reports) == 1, 5)
            stats = client.stats()
            got = client.submap(x=12.8, y=12.8, width=25.6, height=25.6, resolution=RES,
                                encoding="logodds_i16")
    finally:
        assert srv.terminate() == 0
    return reports, stats, got


def test_misaligned_ism_is_corrected_before_fusion(tmp_path: Path) -> None:
    reports, stats, _ = _run_reference_and_cut(tmp_path, "correct")
    report = reports[0]
    assert report.accepted and report.reason == "ok" and report.mode == "correct"
    assert report.corrected is not None
    assert math.hypot(report.corrected.x - TRUE.x, report.corrected.y - TRUE.y) < RES
    assert abs(report.corrected.yaw - TRUE.yaw) < math.radians(1.0)
    assert stats.counters["match_skipped_empty_map"] == 1  # the first ISM: nothing to match
    assert stats.counters["match_accepted"] == 1
    assert stats.extra["match_mean_shift_m"] == pytest.approx(0.36, abs=0.1)


def test_report_mode_publishes_the_correction_and_fuses_as_claimed(tmp_path: Path) -> None:
    reports, _, got = _run_reference_and_cut(tmp_path, "report")
    assert reports[0].accepted and reports[0].mode == "report"
    assert reports[0].dx_m == pytest.approx(TRUE.x - CLAIMED.x, abs=0.15)
    # The map is exactly what fusing both ISMs as claimed gives.
    local = TiledMap("default", "map", TileLattice(RES, 256))
    local.fuse("obstacle", logodds.increments(_prob(PLAN), "prob_f32"),
               GridGeometry(RES, 512, 512))
    local.fuse("obstacle", logodds.increments(_prob(PLAN[150:406, 150:406]), "prob_f32"),
               GridGeometry(RES, 256, 256, CLAIMED))
    want = local.sample(got.geometry, ["obstacle"])
    np.testing.assert_array_equal(got.data, want)


def test_featureless_ism_is_rejected_when_policy_says_so(tmp_path: Path) -> None:
    srv = _matching_server(tmp_path, "correct", on_failure="reject")
    try:
        with srv.client() as client:
            client.publish_ism("ism/mapper/laser/obstacle", _prob(PLAN), resolution=RES,
                               layer="obstacle")
            wait_processed(client, 1)
            window = dict(x=12.8, y=12.8, width=25.6, height=25.6, encoding="logodds_i16")
            before = client.submap(**window)
            floor = np.full((200, 200), 0.2, np.float32)  # empty floor: nothing to match
            client.publish_ism("ism/robot1/laser/obstacle", floor, resolution=RES,
                               origin=Pose2D(5.0, 5.0, 0.1), layer="obstacle")
            counters = wait_processed(client, 2)
            stats = client.stats()
            after = client.submap(**window)
    finally:
        assert srv.terminate() == 0
    assert counters["isms_rejected"] == 1
    assert list(stats.rejected) == ["match_too_few_features"]
    np.testing.assert_array_equal(before.data, after.data)
