"""Tile store: format round trip, atomic writes, corruption -> quarantine, background writer."""

from __future__ import annotations

import json
import logging
import os
import shutil
import struct
import threading
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sogm_service.core import logodds
from sogm_service.core.geodesy import GeoPoint
from sogm_service.core.geometry import TileLattice
from sogm_service.core.map.tilemanager import TileManager
from sogm_service.store.directory import QUARANTINE_DIR, DirectoryStore
from sogm_service.store.format import (
    MAGIC,
    TileHeader,
    tile_file_name,
    tile_from_bytes,
    tile_to_bytes,
)
from sogm_service.store.writer import TileWriter
from sogm_service.wire.errors import StoreLockedError, TileFormatError

T = 32  # small tiles keep the suite fast; one test uses the real 256
RES = 0.05
LAYERS = ["obstacle", "robot1/laser/free"]


def stack(seed: int, n: int = 2, t: int = T) -> np.ndarray:
    """A plausible tile: unknown background, an observed block of clamped log-odds."""
    rng = np.random.default_rng(seed)
    data = np.zeros((n, t, t), dtype=np.int16)
    data[:, t // 4:, : t // 2] = rng.integers(-6907, 6908, (n, t - t // 4, t // 2))
    return data


def open_store(path: Path, **kw: Any) -> DirectoryStore:
    kw.setdefault("frame", "map")
    return DirectoryStore(path, "lab", RES, T, **kw)


def header(i: int = 3, j: int = -12, layers: list[str] = LAYERS, **kw: Any) -> TileHeader:
    fields: dict[str, Any] = dict(map_name="lab", frame="map", i=i, j=j, resolution=RES,
                                  tile_size=T, layers=tuple(layers), stamp=1700000000.5)
    fields.update(kw)
    return TileHeader(**fields)


# -- format ---------------------------------------------------------------------------------
def test_file_name_tags_kind_resolution_size_and_location() -> None:
    assert tile_file_name("lab", 0.05, 256, 3, -12) == "sogm_lab_r0.050_t256_i+0003_j-0012.tile"
    assert tile_file_name("m", 0.0125, 64, -1, 0) == "sogm_m_r0.0125_t64_i-0001_j+0000.tile"


def test_round_trip_through_a_file(tmp_path: Path) -> None:
    data = stack(1)
    with open_store(tmp_path, datum=GeoPoint(48.0, 11.0, 500.0)) as store:
        info = store.write(3, -12, LAYERS, data, 123.25)
        assert info.path.name == "sogm_lab_r0.050_t32_i+0003_j-0012.tile"
    with open_store(tmp_path) as again:
        index = again.index()
        assert list(index) == [(3, -12)]
        tile = again.load(3, -12)
    assert tile is not None
    assert np.array_equal(tile.data, data) and tile.data.dtype == np.int16
    assert tile.data.flags.writeable  # the map fuses into it in place
    h = tile.header
    assert (h.map_name, h.frame, h.index, h.resolution, h.tile_size) == ("lab", "map", (3, -12),
                                                                          RES, T)
    assert h.layers == tuple(LAYERS) and h.stamp == 123.25 and h.scale == logodds.SCALE
    assert h.origin == pytest.approx((3 * RES * T, -12 * RES * T))
    assert h.datum is not None and h.datum.latitude < 48.0 < h.datum.latitude + 0.01
    manager = TileManager(TileLattice(RES, T), 0.5, 1, datum=GeoPoint(48.0, 11.0, 500.0))
    assert h.datum == manager.tile_datum(3, -12)  # events and files agree on the datum
    assert index[(3, -12)].header == h
    layers, arr, stamp = again.loader(3, -12)  # type: ignore[misc]
    assert layers == LAYERS and stamp == 123.25 and np.array_equal(arr, data)


def test_header_is_readable_json_after_a_fixed_prefix(tmp_path: Path) -> None:
    blob = tile_to_bytes(header(), stack(2))
    magic, version, _, hlen = struct.unpack_from("<8sHHI", blob)
    assert magic == MAGIC and version == 1
    fields = json.loads(blob[16:16 + hlen])
    assert fields["shape"] == [2, T, T] and fields["dtype"] == "<i2"
    assert fields["layers"] == LAYERS and fields["i"] == 3 and fields["j"] == -12
    payload = blob[16 + hlen + 4:]
    assert fields["payload_crc32"] == zlib.crc32(payload)
    assert np.array_equal(np.frombuffer(zlib.decompress(payload), "<i2").reshape(2, T, T),
                          stack(2))


def test_wire_bytes_are_the_file_bytes_and_a_replica_stores_them(tmp_path: Path) -> None:
    data = stack(3)
    with open_store(tmp_path / "a") as primary:
        primary.write(0, 0, LAYERS, data, 5.0)
        blob = primary.read_bytes(0, 0)
        assert blob == primary.path_for(0, 0).read_bytes()
    assert blob is not None
    with open_store(tmp_path / "b") as replica:
        info = replica.write_bytes(blob)
        assert info.path.read_bytes() == blob
        loaded = replica.load(0, 0)
        assert loaded is not None and np.array_equal(loaded.data, data)
        with pytest.raises(TileFormatError, match="map 'other'"):
            replica.write_bytes(tile_to_bytes(header(map_name="other"), data))
        assert replica.index() == {(0, 0): replica.indexed()[(0, 0)]}


def test_full_size_tile_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    data = np.zeros((8, 256, 256), dtype=np.int16)
    data[:, :, :150] = rng.integers(-6907, 6908, (8, 256, 150))
    with DirectoryStore(tmp_path, "lab", RES, 256) as store:
        info = store.write(-1, 2, [f"c{k}" for k in range(8)], data, 1.0)
        assert info.size < data.nbytes
        tile = store.load(-1, 2)
    assert tile is not None and np.array_equal(tile.data, data)


def test_encoder_refuses_inconsistent_stacks() -> None:
    with pytest.raises(ValueError, match="shape"):
        tile_to_bytes(header(layers=["a"]), stack(5))
    with pytest.raises(ValueError, match="int16"):
        tile_to_bytes(header(), stack(5).astype(np.int32))
    with pytest.raises(ValueError, match="unique"):
        tile_to_bytes(header(layers=["a", "a"]), stack(5))


# -- corruption -----------------------------------------------------------------------------
def test_every_truncation_and_bit_flip_is_rejected_with_a_reason() -> None:
    blob = tile_to_bytes(header(), stack(6))
    rng = np.random.default_rng(6)
    cuts = sorted({*range(0, 40), *rng.integers(40, len(blob), 60).tolist()})
    for cut in cuts:
        with pytest.raises(TileFormatError) as err:
            tile_from_bytes(blob[:cut])
        assert err.value.reason
    for pos in [*range(0, 24), *rng.integers(24, len(blob), 150).tolist()]:
        flipped = bytearray(blob)
        flipped[pos] ^= 1 << int(rng.integers(8))
        with pytest.raises(TileFormatError):
            tile_from_bytes(bytes(flipped))
    with pytest.raises(TileFormatError, match="trailing"):
        tile_from_bytes(blob + b"\0")
    assert np.array_equal(tile_from_bytes(blob).data, stack(6))


def test_specific_reasons() -> None:
    good = tile_to_bytes(header(), stack(7))
    with pytest.raises(TileFormatError, match="magic"):
        tile_from_bytes(b"PK\x03\x04" + good[4:])
    with pytest.raises(TileFormatError, match="version"):
        tile_from_bytes(good[:8] + b"\x02\x00" + good[10:])
    with pytest.raises(TileFormatError, match="header checksum"):
        tile_from_bytes(good.replace(b'"lab"', b'"lax"'))
    with pytest.raises(TileFormatError, match="payload checksum"):
        tile_from_bytes(good[:-3] + bytes(b ^ 0xFF for b in good[-3:]))


def test_values_outside_the_fixed_point_range_are_rejected() -> None:
    bad = stack(8)
    bad[0, 0, 0] = logodds.MAX_STATE + 1  # would break the no-overflow guarantee of fusion
    with pytest.raises(TileFormatError, match="outside"):
        tile_from_bytes(tile_to_bytes(header(), bad))


def _write_two(store: DirectoryStore) -> tuple[Path, Path]:
    store.write(0, 0, LAYERS, stack(10), 1.0)
    store.write(1, 0, LAYERS, stack(11), 1.0)
    return store.path_for(0, 0), store.path_for(1, 0)


def test_truncated_file_is_quarantined_on_index(tmp_path: Path,
                                                caplog: pytest.LogCaptureFixture) -> None:
    with open_store(tmp_path) as store:
        bad, good = _write_two(store)
        bad.write_bytes(bad.read_bytes()[:-100])  # a torn write without the rename protocol
        with caplog.at_level(logging.WARNING, logger="sogm_service.store.format"):
            index = store.index()
        assert list(index) == [(1, 0)]
        assert not bad.exists() and good.exists()
        moved = tmp_path / QUARANTINE_DIR / bad.name
        assert moved.exists()
        assert "truncated" in (tmp_path / QUARANTINE_DIR / (bad.name + ".reason.txt")).read_text()
        [problem] = store.problems
        assert problem.path == bad and problem.moved_to == moved and "truncated" in problem.reason
        assert bad.name in caplog.text and "truncated" in caplog.text
        assert store.load(0, 0) is None  # gone, never garbage
        assert store.load(1, 0) is not None


def test_bit_flipped_payload_is_quarantined_on_load(tmp_path: Path) -> None:
    with open_store(tmp_path) as store:
        bad, _ = _write_two(store)
        raw = bytearray(bad.read_bytes())
        raw[-10] ^= 0x40
        bad.write_bytes(bytes(raw))
        assert set(store.index()) == {(0, 0), (1, 0)}  # the header alone still checks out
        assert store.load(0, 0) is None
        assert (tmp_path / QUARANTINE_DIR / bad.name).exists()
        assert "payload checksum" in store.problems[0].reason
        assert set(store.indexed()) == {(1, 0)}
        # A fresh write of the same tile works and is loadable again.
        store.write(0, 0, LAYERS, stack(12), 2.0)
        tile = store.load(0, 0)
        assert tile is not None and np.array_equal(tile.data, stack(12))


def test_misnamed_or_foreign_files_are_quarantined_not_loaded(tmp_path: Path) -> None:
    with open_store(tmp_path) as store:
        # A valid tile (1, 1) copied under the name of tile (0, 0).
        (tmp_path / tile_file_name("lab", RES, T, 0, 0)).write_bytes(
            tile_to_bytes(header(i=1, j=1), stack(13)))
        # A header claiming another frame.
        (tmp_path / tile_file_name("lab", RES, T, 2, 2)).write_bytes(
            tile_to_bytes(header(i=2, j=2, frame="odom"), stack(13)))
        # Garbage with a tile name; and another map's tile, which is simply not ours.
        (tmp_path / tile_file_name("lab", RES, T, 3, 3)).write_bytes(b"hello")
        other = tmp_path / tile_file_name("other", RES, T, 0, 0)
        other.write_bytes(tile_to_bytes(header(map_name="other", i=0, j=0), stack(13)))
        assert store.index() == {}
        reasons = sorted(p.reason for p in store.problems)
        assert len(reasons) == 3
        assert any("file name" in r for r in reasons)
        assert any("frame 'odom'" in r for r in reasons)
        assert any("magic" in r or "truncated" in r for r in reasons)
        assert other.exists()
        assert len(list((tmp_path / QUARANTINE_DIR).glob("*.tile"))) == 3


def test_quarantine_keeps_every_rejected_version(tmp_path: Path) -> None:
    with open_store(tmp_path) as store:
        for _ in range(2):
            store.path_for(0, 0).write_bytes(b"junk")
            store.index()
        assert len(list((tmp_path / QUARANTINE_DIR).glob("sogm_*"))) == 4  # 2 files + reasons


def test_readonly_store_reports_but_never_moves(tmp_path: Path) -> None:
    with open_store(tmp_path) as store:
        bad, _ = _write_two(store)
    bad.write_bytes(bad.read_bytes()[:50])
    ro = open_store(tmp_path, readonly=True)
    assert set(ro.index()) == {(1, 0)}
    assert bad.exists() and not (tmp_path / QUARANTINE_DIR).exists()
    assert ro.problems[0].moved_to is None
    with pytest.raises(PermissionError):
        ro.write(0, 0, LAYERS, stack(1), 1.0)


# -- atomicity ------------------------------------------------------------------------------
def test_a_failed_rename_leaves_the_old_file_and_no_temp(tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    with open_store(tmp_path) as store:
        store.write(0, 0, LAYERS, stack(20), 1.0)
        before = store.path_for(0, 0).read_bytes()

        def crash(*_: Any) -> None:
            raise OSError("simulated crash before rename")

        monkeypatch.setattr(os, "replace", crash)
        with pytest.raises(OSError, match="simulated"):
            store.write(0, 0, LAYERS, stack(21), 2.0)
        monkeypatch.undo()
        assert store.path_for(0, 0).read_bytes() == before
        assert [p.name for p in tmp_path.iterdir() if ".tmp-" in p.name] == []


def test_a_temp_left_by_a_killed_writer_is_ignored_and_cleaned(tmp_path: Path) -> None:
    with open_store(tmp_path) as store:
        store.write(0, 0, LAYERS, stack(22), 1.0)
        final = store.path_for(0, 0)
        # A crash mid-write: half of a newer tile in a temp file, never renamed.
        newer = tile_to_bytes(header(i=0, j=0), stack(23))
        tmp = final.with_name(f".{final.name}.tmp-99999-0")
        tmp.write_bytes(newer[: len(newer) // 2])
    with open_store(tmp_path) as restarted:
        assert list(restarted.index()) == [(0, 0)]
        assert not tmp.exists()
        tile = restarted.load(0, 0)
        assert tile is not None and np.array_equal(tile.data, stack(22))
        assert restarted.problems == []


def test_one_writer_per_directory(tmp_path: Path) -> None:
    store = open_store(tmp_path)
    with pytest.raises(StoreLockedError):
        open_store(tmp_path)
    open_store(tmp_path, readonly=True)  # inspection needs no lock
    store.close()
    open_store(tmp_path).close()  # released


# -- background writer ----------------------------------------------------------------------
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


GOLDEN = Path(__file__).parent / "data" / "sogm_golden_r0.050_t16_i+0003_j-0002.tile"


def test_a_tile_file_written_before_the_package_layout_loads_and_reencodes_byte_for_byte(
        tmp_path: Path) -> None:
    """``tests/data`` holds a tile written by the code of commit 55775f4 (flat modules): the
    file format must not have moved with the code."""
    blob = GOLDEN.read_bytes()
    tile = tile_from_bytes(blob)
    h = tile.header
    assert (h.map_name, h.frame, h.index, h.resolution, h.tile_size) == \
        ("golden", "map", (3, -2), 0.05, 16)
    assert h.layers == ("robot1/laser/obstacle", "floor", "pallet")
    assert h.stamp == 1234.5 and h.written_unix == 1764400000.0
    assert h.datum is not None and (h.datum.latitude, h.datum.longitude) == (48.1, 11.5)
    expected = np.load(GOLDEN.with_name("golden_tile_layers.npy"))
    np.testing.assert_array_equal(tile.data, expected)
    assert tile_to_bytes(h, tile.data) == blob  # same header + data -> the very same bytes
    shutil.copy(GOLDEN, tmp_path / GOLDEN.name)
    with DirectoryStore(tmp_path, "golden", 0.05, 16) as store:
        assert list(store.index()) == [(3, -2)]
        loaded = store.load(3, -2)
        assert loaded is not None
        np.testing.assert_array_equal(loaded.data, expected)
