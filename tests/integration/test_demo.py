"""The embedded demo: a short headless run writes every promised file and maps well."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from sogm_service.apps.demo import DemoResult, run_demo

pytestmark = pytest.mark.integration

# Per-class IoU over observed cells that a short run must reach (measured: floor 0.98,
# obstacle 0.8, shelf 0.6-0.7 for 20-60 simulated seconds).
MIN_IOU = {"floor": 0.9, "obstacle": 0.6}


# The short run both layer modes make (about 15-20 s wall each on 2 loaded cores).
SHORT_RUN: dict[str, Any] = dict(world="warehouse", robots=2, duration_s=8.0, rate_hz=4.0,
                                 seed=1, speed=4.0, progress=False)
# Per-robot layers read by class patterns carry the same evidence as shared layers; only the
# clamp differs (a shared layer clamps after each ISM, a class clamps its robots' sum), which
# moves a class's IoU by less than this (measured: equal to 4 decimals).
PER_ROBOT_IOU_TOLERANCE = 0.03


@pytest.fixture(scope="module")
def shared_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[DemoResult, Path]:
    """The default demo (every robot's ISMs of a class in one shared layer), run once."""
    out = tmp_path_factory.mktemp("demo") / "demo"
    return run_demo(out=out, **SHORT_RUN), out


def test_short_demo_writes_every_file_and_reaches_the_iou(
        shared_run: tuple[DemoResult, Path]) -> None:
    result, out = shared_run
    summary = json.loads((out / "summary.json").read_text())
    assert summary["isms_fused"] == summary["isms_published"] > 0
    assert summary["isms_rejected"] == 0
    assert summary["tile_switches"] >= 2  # each robot's first pose at least
    for name in ["classes.png", "fused_bayes.png", "fused_max.png", "ground_truth.png",
                 "submap_robot1.png", "submap_robot2.png", "tile_events.log",
                 "layer_obstacle.png", "layer_floor.png", "supercells.png"]:
        assert (out / name).stat().st_size > 0, name
    assert len((out / "tile_events.log").read_text().splitlines()) == summary["tile_switches"]
    assert list((out / "tiles").glob("*.tile")), "the tile store was not flushed"
    for layer, minimum in MIN_IOU.items():
        assert result.iou[layer] > minimum, (layer, result.iou)
    assert result.submap_latency_ms["p50"] > 0
    assert summary["layer_mode"] == "shared"
    assert summary["classes"]["obstacle"] == {"entry": "obstacle", "members": ["obstacle"]}


def test_per_robot_layers_demo_reads_classes_of_every_robot_at_the_shared_iou(
        tmp_path: Path, shared_run: tuple[DemoResult, Path]) -> None:
    """``demo --per-robot-layers``: the fleet sends no layer, so the map holds each robot's
    ``<robot>/<sensor>/<class>``; the demo reads them by ``*/*/<class>`` and scores the same."""
    shared, _ = shared_run
    out = tmp_path / "demo"
    result = run_demo(out=out, per_robot_layers=True, **SHORT_RUN)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["layer_mode"] == "per_robot"
    assert summary["isms_fused"] == summary["isms_published"] == shared.isms_published > 0
    assert summary["isms_rejected"] == 0
    classes = summary["classes"]
    assert {"obstacle", "floor", "person"} <= classes.keys()
    for name, cls in classes.items():
        assert cls["entry"] == f"*/*/{name}"
        robots = {m.split("/")[0] for m in cls["members"]}
        assert robots == {"robot1", "robot2"}, (name, cls)  # every robot its own layer
        assert all(m.count("/") == 2 and m.endswith(f"/{name}") for m in cls["members"])
    assert classes["obstacle"]["members"] == ["robot1/laser/obstacle", "robot2/laser/obstacle"]
    assert summary["moving"]["layer"] == "*/*/person"
    assert result.iou.keys() == shared.iou.keys()  # per class, as with shared layers
    for name, iou in shared.iou.items():
        assert abs(result.iou[name] - iou) <= PER_ROBOT_IOU_TOLERANCE, (name, result.iou,
                                                                        shared.iou)
    for name in ["layer_obstacle.png", "layer_floor.png", "classes.png", "fused_max.png",
                 "submap_robot1.png", "supercells.png"]:
        assert (out / name).stat().st_size > 0, name
    assert result.supercells == shared.supercells


def test_secure_demo_runs_end_to_end_through_mtls_and_access_control(tmp_path: Path) -> None:
    """``demo --secure``: every session from its identity's config of a fresh dev PKI."""
    out = tmp_path / "demo"
    result = run_demo(world="warehouse", robots=2, duration_s=4.0, rate_hz=4.0, seed=2,
                      out=out, realtime=False, progress=False, secure=True)
    assert result.isms_fused == result.isms_published > 0 and result.isms_rejected == 0
    assert result.tile_switches >= 2  # the viewer identity receives events
    server_conf = (out / "pki" / "server.json5").read_text()
    assert "tls/" in server_conf and "access_control" in server_conf
    for name in ("ca.crt", "robot1.crt", "robot2.key", "viewer.json5"):
        assert (out / "pki" / name).exists(), name


def test_demo_drives_a_running_server_through_a_zenoh_config_file(tmp_path: Path) -> None:
    """``demo --zenoh-config``: no embedded server; robots and queries open their sessions
    from the file and fill a running server's map."""
    from tests.conftest import start_server

    srv = start_server(tmp_path, {"map": {"name": "demo"}})
    try:
        config = tmp_path / "site.json5"
        config.write_text(json.dumps({"mode": "client", "connect": {"endpoints": [srv.endpoint]},
                                      "scouting": {"multicast": {"enabled": False}}}))
        out = tmp_path / "demo"
        result = run_demo(world="warehouse", robots=2, duration_s=4.0, rate_hz=4.0, seed=3,
                          out=out, realtime=False, progress=False, zenoh_config=config)
        assert result.isms_fused == result.isms_published > 0
        assert (out / "classes.png").stat().st_size > 0
        from sogm_service.client import MapClient

        with MapClient.connect(srv.endpoint, map_name="demo") as client:
            assert client.stats().counters["isms_fused"] == result.isms_fused
    finally:
        assert srv.terminate() == 0
