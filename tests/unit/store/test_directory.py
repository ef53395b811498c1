"""The tile store directory (store/directory): atomic writes, one writer per directory, damaged
or foreign files quarantined, never loaded.

Its helpers (``stack``, ``open_store``, ``header``) serve the format and writer tests too."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sogm_service.store.directory import QUARANTINE_DIR, DirectoryStore
from sogm_service.wire.errors import StoreLockedError
from sogm_service.wire.tilefile import TileHeader, tile_file_name, tile_to_bytes

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




# -- corruption -----------------------------------------------------------------------------


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
