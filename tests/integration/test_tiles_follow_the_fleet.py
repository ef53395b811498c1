"""Tiles that follow the fleet, over real server processes: events, budget, crash, replication."""

from __future__ import annotations

import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice
from sogm_service.core.map.tiles import TiledMap
from sogm_service.store.directory import DirectoryStore
from sogm_service.wire.messages import TileEvent
from tests.conftest import start_server, wait_processed, wait_until

pytestmark = pytest.mark.integration

SPAN = 256 * 0.05  # 12.8 m tiles at the default resolution


def test_robot_across_tile_edges_gives_exactly_the_expected_events(tmp_path: Path) -> None:
    srv = start_server(tmp_path, {"tiles": {"hysteresis_m": 1.0}})
    events: list[TileEvent] = []
    try:
        with srv.client() as client:
            client.subscribe_tile_events(events.append)
            time.sleep(0.3)  # let the subscription reach the server
            path = [(1.0, 1.0),                                  # first pose: tile (0, 0)
                    (12.0, 1.0), (13.6, 1.0), (12.5, 1.0), (13.5, 1.2),  # zig-zag on the edge
                    (12.2, 1.0), (13.7, 1.0),                      # still within hysteresis
                    (14.0, 1.0),                                   # 1.2 m past: tile (1, 0)
                    (12.1, 1.0), (12.9, 1.0),                      # back within hysteresis
                    (11.5, 1.0),                                   # 1.3 m back: tile (0, 0)
                    (11.5, -0.5), (11.5, 0.5)]                     # the y edge, inside band
            for k, (x, y) in enumerate(path):
                client.publish_pose("robot1", x, y, stamp=float(k))
            assert wait_until(lambda: len(events) >= 3, 10)
            time.sleep(0.5)  # nothing more may come
            robots = client.robots()
    finally:
        assert srv.terminate() == 0
    assert [(e.robot, e.i, e.j) for e in events] == [
        ("robot1", 0, 0), ("robot1", 1, 0), ("robot1", 0, 0)]
    assert events[1].origin.x == pytest.approx(SPAN) and events[1].stamp == 7.0
    assert events[1].name.endswith("i+0001_j+0000")
    assert [(e.robot, e.i, e.j) for e in robots.robots] == [("robot1", 0, 0)]


def test_geo_referenced_events_carry_the_tile_datum(tmp_path: Path) -> None:
    datum = {"latitude": 45.0, "longitude": 8.0, "altitude": 100.0}
    srv = start_server(tmp_path, {"map": {"datum": datum}, "tiles": {"hysteresis_m": 0.5}})
    events: list[TileEvent] = []
    try:
        with srv.client() as client:
            client.subscribe_tile_events(events.append)
            time.sleep(0.3)
            client.publish_pose("r", 1.0, 1.0)
            client.publish_pose("r", SPAN + 1.0, 1.0)
            assert wait_until(lambda: len(events) >= 2, 10)
    finally:
        assert srv.terminate() == 0
    first, second = events[0].datum, events[1].datum
    assert first is not None and second is not None
    assert first.latitude == pytest.approx(45.0) and first.longitude == pytest.approx(8.0)
    # One tile east: 12.8 m of longitude at 45 degrees (about 78.85 km per degree).
    assert (second.longitude - first.longitude) * 78_846.8 == pytest.approx(SPAN, rel=2e-3)
    assert second.latitude == pytest.approx(45.0, abs=1e-6)


def _checker_isms(n_tiles: int, seed: int) -> list[tuple[np.ndarray, Pose2D]]:
    """One random 256x256 prob_u8 ISM per tile of an n x n block, half-tile offset."""
    rng = np.random.default_rng(seed)
    out = []
    for j in range(n_tiles):
        for i in range(n_tiles):
            data = rng.integers(0, 256, (256, 256), dtype=np.uint8)
            out.append((data, Pose2D((i + 0.5) * SPAN, (j + 0.5) * SPAN, 0.0)))
    return out


def test_map_larger_than_the_memory_budget_reads_back_identically(tmp_path: Path) -> None:
    isms = _checker_isms(6, seed=3)  # touches 7x7 = 49 tiles of 128 KB each: 6.4 MB
    srv = start_server(tmp_path, {"storage": {"directory": str(tmp_path / "store"),
                                              "memory_budget_mb": 1.0,
                                              "checkpoint_interval_s": 0.5}})
    try:
        with srv.client(timeout=10) as client:
            for data, origin in isms:
                client.publish_ism("ism/r/laser/obstacle", data, resolution=0.05,
                                   origin=origin)
            wait_processed(client, len(isms), timeout=60)
            stats = client.stats()
            got = client.submap(x=3.5 * SPAN, y=3.5 * SPAN, width=7 * SPAN, height=7 * SPAN,
                                encoding="logodds_i16")
    finally:
        assert srv.terminate() == 0
    assert stats.counters.get("tiles_evicted", 0) > 20
    assert stats.extra["resident_mb"] <= 1.0 + 0.2  # one tile of slack per ISM in flight

    unbounded = TiledMap("default", "map", TileLattice(0.05, 256))
    for data, origin in isms:
        unbounded.fuse("r/laser/obstacle", logodds.increments(data, "prob_u8"),
                       GridGeometry(0.05, 256, 256, origin))
    window = GridGeometry(0.05, got.geometry.width, got.geometry.height, got.geometry.origin)
    want = unbounded.sample(window, ["r/laser/obstacle"])
    np.testing.assert_array_equal(got.data, want)


def _prefix_count(tile: np.ndarray, inc: int, limit: int) -> int | None:
    """k such that every cell equals clamp(k * inc), or None."""
    k = round(float(tile.flat[0]) / inc)
    return k if np.array_equal(tile, np.full_like(tile, min(k * inc, limit))) else None


def test_sigkill_under_load_restarts_from_the_last_checkpoint(tmp_path: Path) -> None:
    store_dir = tmp_path / "store"
    sections = {"storage": {"directory": str(store_dir), "checkpoint_interval_s": 0.3}}
    # 2x2 tiles, one small positive increment per ISM: after k ISMs each cell is k * inc.
    data = np.full((512, 512), 134, np.uint8)
    inc = int(logodds.increment_lut("prob_u8")[134])
    _, hi = logodds.clamp_limits()
    srv = start_server(tmp_path, sections)
    stop = threading.Event()
    with srv.client() as client:
        for _ in range(10):
            client.publish_ism("ism/r/laser/obstacle", data, resolution=0.05)
        wait_processed(client, 10)
        assert wait_until(lambda: client.stats().extra.get("dirty_tiles") == 0
                          and client.stats().extra.get("writes_pending") == 0, 10)

        def load() -> None:  # keep ingesting while the server is killed
            while not stop.is_set():
                client.publish_ism("ism/r/laser/obstacle", data, resolution=0.05)
                time.sleep(0.01)

        pusher = threading.Thread(target=load)
        pusher.start()
        time.sleep(1.0)
        srv.proc.send_signal(signal.SIGKILL)
        srv.proc.wait(10)
        stop.set()
        pusher.join(10)

    # Every tile file loads and its checksums hold.
    with DirectoryStore(store_dir, "default", 0.05, 256) as store:
        index = store.index()
        assert store.problems == []
        assert sorted(index) == [(0, 0), (0, 1), (1, 0), (1, 1)]
        counts = []
        for i, j in index:
            stored = store.load(i, j)
            assert stored is not None
            k = _prefix_count(stored.data[0], inc, hi)
            assert k is not None, "a tile holds a torn state, not a checkpoint"
            counts.append(k)
    assert min(counts) >= 10  # everything checkpointed before the load is still there

    # The restarted server serves exactly what the files hold.
    srv2 = start_server(tmp_path, sections, name="restarted")
    try:
        with srv2.client() as client:
            sub = client.submap(x=SPAN, y=SPAN, width=2 * SPAN, height=2 * SPAN,
                                encoding="logodds_i16")
    finally:
        assert srv2.terminate() == 0
    quadrant = sub.data[0, :256, :256]
    assert _prefix_count(quadrant, inc, hi) == counts[sorted(index).index((0, 0))]


def test_truncated_tile_file_is_skipped_with_a_clear_report(tmp_path: Path) -> None:
    store_dir = tmp_path / "store"
    sections = {"storage": {"directory": str(store_dir)}}
    srv = start_server(tmp_path, sections)
    with srv.client() as client:
        client.publish_ism("ism/r/laser/obstacle", np.full((512, 256), 220, np.uint8),
                           resolution=0.05)
        wait_processed(client, 1)
    assert srv.terminate() == 0  # SIGTERM flushes both tiles
    files = sorted(store_dir.glob("*.tile"))
    assert len(files) == 2
    blob = files[0].read_bytes()
    files[0].write_bytes(blob[:len(blob) // 2])

    srv2 = start_server(tmp_path, sections, name="second")
    try:
        with srv2.client() as client:
            stats = client.stats()
            info = client.info()
            sub = client.submap(x=6.4, y=12.8, width=12.8, height=25.6)
    finally:
        assert srv2.terminate() == 0
    assert stats.counters.get("store_problems") == 1
    assert len(info.tiles) == 1
    assert "truncated" in srv2.log() or "length" in srv2.log()
    assert len(list((store_dir / "quarantine").glob("*.tile"))) == 1
    p = sub.probabilities()[0]
    halves = [p[:256], p[256:]]
    known = [bool((np.abs(h - 0.5) > 1e-3).any()) for h in halves]
    assert sorted(known) == [False, True]  # one tile served, the corrupt one unknown


def test_second_server_copies_the_map_through_tiles(tmp_path: Path) -> None:
    first = start_server(tmp_path, {"map": {"name": "site"}}, name="first")
    window = dict(x=2.0, y=1.0, yaw=0.7, width=16.0, height=12.0, resolution=0.08)
    try:
        with first.client() as c1:
            c1.map_name = "site"
            rng = np.random.default_rng(5)
            c1.publish_ism("ism/r/laser/obstacle", rng.integers(0, 256, (300, 400), np.uint8),
                           resolution=0.05, origin=Pose2D(-3.0, -2.0, 0.2))
            c1.publish_ism("ism/r/cam/floor", rng.random((100, 100)).astype(np.float32),
                           resolution=0.1, origin=Pose2D(2.0, 1.0, -0.4))
            wait_processed(c1, 2)
            want = c1.submap(**window, encoding="logodds_i16")
            first_id = c1.info().server_id
        second = start_server(tmp_path, {"map": {"name": "site"},
                                         "tiles": {"replicate_on_start": True},
                                         "zenoh": {"connect": [first.endpoint]}},
                              name="second", servers=2)
    finally:
        assert first.terminate() == 0  # from here on only the copy can answer
    try:
        with second.client() as c2:
            c2.map_name = "site"
            info = c2.info()
            stats = c2.stats()
            got = c2.submap(**window, encoding="logodds_i16")
    finally:
        assert second.terminate() == 0
    assert info.server_id != first_id
    assert stats.counters.get("replica_tiles_copied", 0) >= 4
    assert got.layers == want.layers
    np.testing.assert_array_equal(got.data, want.data)


def test_sigterm_flushes_every_queued_ism_to_the_store(tmp_path: Path) -> None:
    store_dir = tmp_path / "store"
    sections = {"storage": {"directory": str(store_dir), "checkpoint_interval_s": 60.0}}
    data = np.full((300, 300), 134, np.uint8)
    inc = int(logodds.increment_lut("prob_u8")[134])
    srv = start_server(tmp_path, sections)
    with srv.client() as client:
        for _ in range(25):
            client.publish_ism("ism/r/laser/obstacle", data, resolution=0.05)
        # SIGTERM stops accepting work: first make sure all 25 have arrived.
        assert wait_until(lambda: client.stats().counters.get("isms_received") == 25, 10)
    # No checkpoint has run (60 s interval): only the shutdown flush can save these.
    assert srv.terminate(timeout=15) == 0
    with DirectoryStore(store_dir, "default", 0.05, 256) as store:
        stored = store.load(0, 0)
    assert stored is not None
    assert _prefix_count(stored.data[0, :200, :200], inc, 10**6) == 25
