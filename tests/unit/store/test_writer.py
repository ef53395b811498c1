"""The background tile writer (store/writer): snapshots persisted off the caller's thread,
coalesced, frozen; errors reported."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sogm_service.core.geometry import TileLattice
from sogm_service.core.map.tiles import TiledMap
from sogm_service.store.directory import QUARANTINE_DIR, DirectoryStore
from sogm_service.store.writer import TileWriter
from tests.unit.service.cluster.test_handover import mild_ism
from tests.unit.store.test_directory import LAYERS, RES, T, open_store, stack
from tests.unit.store.test_format import MARK_RES, MARK_T


def test_writer_persists_snapshots_and_flush_waits(tmp_path: Path) -> None:
    saved: list[tuple[tuple[int, int], Any]] = []
    with open_store(tmp_path) as store:
        writer = TileWriter(store, on_saved=lambda idx, tok: saved.append((idx, tok)))
        for k in range(6):
            writer.submit(k, -k, LAYERS, stack(30 + k), 10.0 + k, token=k)
        assert writer.flush(timeout=10.0)
        assert writer.pending() == 0
        assert sorted(saved) == [((k, -k), k) for k in range(6)]
        assert writer.close(timeout=5.0)
    with open_store(tmp_path) as again:
        assert set(again.index()) == {(k, -k) for k in range(6)}
        for k in range(6):
            tile = again.load(k, -k)
            assert tile is not None and np.array_equal(tile.data, stack(30 + k))
            assert tile.header.stamp == 10.0 + k
    with pytest.raises(RuntimeError, match="closed"):
        writer.submit(0, 0, LAYERS, stack(1), 1.0)


class _GatedStore(DirectoryStore):
    """A store whose writes wait for a gate: lets a test hold the writer mid-write."""

    def __init__(self, *a: Any, **kw: Any) -> None:
        super().__init__(*a, **kw)
        self.gate = threading.Event()
        self.entered = threading.Event()

    def write(self, *a: Any, **kw: Any) -> Any:
        self.entered.set()
        assert self.gate.wait(10.0)
        return super().write(*a, **kw)


def test_submit_never_waits_for_disk_and_coalesces(tmp_path: Path) -> None:
    store = _GatedStore(tmp_path, "lab", RES, T, frame="map")
    saved: list[Any] = []
    writer = TileWriter(store, on_saved=lambda idx, tok: saved.append((idx, tok)))
    try:
        writer.submit(0, 0, LAYERS, stack(40), 1.0, token="v1")
        assert store.entered.wait(5.0)  # the writer is stuck in the first write
        for v in ("v2", "v3", "v4"):  # returns at once although the disk is "busy"
            writer.submit(0, 0, LAYERS, stack(41) + len(v), 2.0, token=v)
        assert writer.stats.coalesced == 2
        assert not writer.flush(timeout=0.05)  # still blocked: flush reports the timeout
        assert writer.is_pending(0, 0)
        # An evicted tile reloads from the newest pending snapshot, not the old file.
        layers, data, stamp = writer.loader(0, 0)  # type: ignore[misc]
        assert layers == LAYERS
        assert np.array_equal(data, stack(41) + 2) and data.flags.writeable and stamp == 2.0
        store.gate.set()
        assert writer.flush(timeout=10.0)
    finally:
        store.gate.set()
        writer.close(5.0)
        store.close()
    assert saved == [((0, 0), "v1"), ((0, 0), "v4")]
    assert writer.stats.written == 2
    with open_store(tmp_path) as again:
        tile = again.load(0, 0)
        assert tile is not None and np.array_equal(tile.data, stack(41) + 2)


def test_submitted_snapshot_is_frozen(tmp_path: Path) -> None:
    with open_store(tmp_path) as store:
        writer = TileWriter(store)
        snap = stack(50)
        writer.submit(0, 0, LAYERS, snap, 1.0)
        with pytest.raises(ValueError, match="read-only"):
            snap[0, 0, 0] = 1  # a live array passed by mistake fails loudly
        with pytest.raises(ValueError, match="shape"):
            writer.submit(0, 0, ["one"], stack(50), 1.0)
        assert writer.close(5.0)


def test_write_errors_are_reported_and_the_thread_survives(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    errors: list[Any] = []
    saved: list[Any] = []
    with open_store(tmp_path) as store:
        writer = TileWriter(store, on_saved=lambda i, t: saved.append(t),
                            on_error=lambda i, t, e: errors.append((i, t, str(e))))
        real = store.write

        def failing(i: int, j: int, *a: Any) -> Any:
            if (i, j) == (9, 9):
                raise OSError("No space left on device")
            return real(i, j, *a)

        monkeypatch.setattr(store, "write", failing)
        writer.submit(9, 9, LAYERS, stack(60), 1.0, token="a")
        writer.submit(1, 1, LAYERS, stack(61), 1.0, token="b")
        assert writer.flush(10.0)
        assert errors == [((9, 9), "a", "No space left on device")]
        assert saved == ["b"] and writer.stats.errors == 1
        assert "No space" in (writer.stats.last_error or "")
        assert writer.close(5.0)


def test_loads_during_rewrites_never_see_a_torn_file(tmp_path: Path) -> None:
    """Readers racing the writer's renames get the old or the new tile, never a reject."""
    with open_store(tmp_path) as store:
        writer = TileWriter(store)
        versions = [stack(70 + k) for k in range(3)]
        writer.submit(0, 0, LAYERS, versions[0].copy(), 0.0)
        assert writer.flush(5.0)
        for k in range(150):
            writer.submit(0, 0, LAYERS, versions[k % 3].copy(), float(k))
            tile = store.load(0, 0)
            assert tile is not None
            assert any(np.array_equal(tile.data, v) for v in versions)
        assert writer.close(10.0)
        assert store.problems == [] and not (tmp_path / QUARANTINE_DIR).exists()


def test_marks_survive_evict_and_load_back_through_writer_and_store(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    store = _GatedStore(tmp_path, "lab", MARK_RES, MARK_T, frame="map")
    store.gate = threading.Event()
    writer = TileWriter(store)
    tiled = TiledMap("lab", "map", TileLattice(MARK_RES, MARK_T), loader=writer.loader)
    try:
        for n, key in enumerate(["ism/r1", "ism/r2", "ism/r1"]):
            inc, geom = mild_ism(rng, 10, 4)  # spans tiles (0, 0) and (1, 0)
            tiled.fuse("l", inc, geom, "nearest", float(n + 1), mark=(key, (n + 1.0, 100 + n)))
        expected = {"ism/r1": (3.0, 102), "ism/r2": (2.0, 101)}
        for index in [(0, 0), (1, 0)]:
            assert tiled.tiles[index].applied == expected

        def submit(snap: Any) -> None:
            writer.submit(snap.index[0], snap.index[1], snap.layers, snap.data, snap.stamp,
                          token=snap.version, applied=snap.applied)

        # Evicted while its snapshot still waits for the disk: back from the writer's queue.
        tiled.evict((0, 0), before=submit)
        assert writer.is_pending(0, 0) and not store.path_for(0, 0).exists()
        again = tiled.get_tile((0, 0))
        assert again is not None and again.applied == expected
        store.gate.set()
        assert writer.flush(10.0)
        tiled.evict((0, 0), before=submit)
        tiled.evict((1, 0), before=submit)
        assert writer.flush(10.0) and not tiled.tiles
        for index in [(0, 0), (1, 0)]:  # now from the files
            tile = tiled.get_tile(index)
            assert tile is not None and tile.applied == expected
        # A restart: a new map over the same directory, marks from the files only.
        fresh = TiledMap("lab", "map", TileLattice(MARK_RES, MARK_T), loader=store.loader)
        fresh.stored = set(store.index())
        tile = fresh.get_tile((1, 0))
        assert tile is not None and tile.applied == expected
        # A further fuse updates one key's mark; the other comes from the file.
        inc, geom = mild_ism(rng, 10, 4)
        fresh.fuse("l", inc, geom, "nearest", 4.0, mark=("ism/r2", (4.0, 103)))
        assert tile.applied == {"ism/r1": (3.0, 102), "ism/r2": (4.0, 103)}
    finally:
        store.gate.set()
        writer.close(10.0)
        store.close()
