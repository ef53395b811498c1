"""A tile's version moves exactly when its content changes (core/map/tile.py: versions), and a
tile loaded back from the store keeps it (the ``tile_version`` header field)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice
from sogm_service.core.map.tile import TileSnapshot
from sogm_service.core.map.tiles import TiledMap
from sogm_service.core.map.tiletypes import Loader
from sogm_service.store.directory import DirectoryStore
from sogm_service.wire import tilefile
from sogm_service.wire.errors import TileFormatError
from sogm_service.wire.tilefile import Expectation, tile_from_bytes, tile_header, tile_to_bytes

RES, T = 0.05, 16
SPAN = RES * T


def new_map(loader: Loader | None = None, first_version: int | None = None) -> TiledMap:
    return TiledMap("test", "map", TileLattice(RES, T), loader=loader,
                    first_version=first_version)


def block(i: int, j: int, w: int = 4, h: int = 4) -> GridGeometry:
    return GridGeometry(RES, w, h, Pose2D(i * SPAN + 2 * RES, j * SPAN + 2 * RES, 0.0))


def full(value: int, w: int = 4, h: int = 4) -> np.ndarray:
    return np.full((h, w), value, np.int16)


def versions(m: TiledMap) -> dict[tuple[int, int], int]:
    return {index: t.version for index, t in m.tiles.items()}


def test_a_fuse_that_changes_cells_bumps_only_the_tiles_it_wrote() -> None:
    m = new_map()
    m.fuse("a", full(300), block(0, 0))
    m.fuse("a", full(300), block(1, 0))
    before = versions(m)
    m.fuse("a", full(200), block(1, 0))
    after = versions(m)
    assert after[(0, 0)] == before[(0, 0)]
    assert after[(1, 0)] > before[(1, 0)]


def test_an_all_unknown_ism_leaves_the_version_and_the_planes() -> None:
    m = new_map()
    m.fuse("a", full(300), block(0, 0))
    before, data = versions(m), m.tiles[(0, 0)].planes[0].copy()
    m.fuse("a", full(0), block(0, 0), stamp=5.0)  # unknown cells: increments of 0
    m.fuse("b", full(0), block(0, 0), stamp=6.0)  # a new layer, all unknown
    assert versions(m) == before
    assert np.array_equal(m.tiles[(0, 0)].planes[0], data)


def test_an_all_unknown_ism_creates_no_tile_and_no_version() -> None:
    m = new_map()
    assert m.fuse("a", full(0), block(3, 3)) == []
    assert (3, 3) not in m.tiles


def test_versions_increase_strictly_and_start_beyond_an_earlier_run() -> None:
    m = new_map()
    m.fuse("a", full(300), block(0, 0))
    first = m.tiles[(0, 0)].version
    later = new_map()  # a restarted server: its clock starts at the wall clock, later
    later.fuse("a", full(300), block(0, 0))
    assert later.tiles[(0, 0)].version > first
    seen = []
    for k in range(5):
        m.fuse("a", full(10 + k), block(0, 0))
        seen.append(m.tiles[(0, 0)].version)
    assert seen == sorted(set(seen))


def test_a_decaying_layer_keeps_its_version_while_only_the_clock_moves() -> None:
    """Its content is the tile's planes and decay stamps; the read decays them to the clock."""
    m = new_map()
    m.set_forget({"person": 10.0})
    m.fuse("person", full(2000), block(0, 0), stamp=0.0)
    m.fuse("wall", full(500), block(1, 0), stamp=0.0)
    before = versions(m)
    m.advance_clock(30.0)
    read = m.mosaic((0, 0, T, T), [m.layer_id("person")])
    assert 0 < int(read.max()) < 2000  # reads decayed...
    assert versions(m) == before  # ...yet nothing held changed


def test_a_write_that_decays_a_layer_in_place_bumps_even_with_unknown_cells() -> None:
    m = new_map()
    m.set_forget({"person": 10.0})
    m.fuse("person", full(2000), block(0, 0), stamp=0.0)
    v0 = m.tiles[(0, 0)].version
    m.fuse("person", full(0), block(0, 0), stamp=0.1)  # within h/32: no decay, no change
    assert m.tiles[(0, 0)].version == v0
    m.fuse("person", full(0), block(0, 0), stamp=20.0)  # decays in place: cells change
    assert m.tiles[(0, 0)].version > v0
    assert int(m.tiles[(0, 0)].planes[0].max()) < 2000


def test_a_tile_loaded_back_from_the_store_keeps_its_version(tmp_path: Path) -> None:
    store = DirectoryStore(tmp_path, "test", RES, T, frame="map")
    m = new_map(loader=store.loader)
    m.fuse("a", full(300), block(0, 0), stamp=1.0)
    version = m.tiles[(0, 0)].version

    def save(snap: TileSnapshot) -> None:
        store.write(0, 0, snap.layers, snap.data, snap.stamp, version=snap.version)

    m.evict((0, 0), before=save)
    assert (0, 0) not in m.tiles
    store.close()

    restarted = DirectoryStore(tmp_path, "test", RES, T, frame="map")
    again = new_map(loader=restarted.loader, first_version=1)  # a clock far behind
    again.stored = set(restarted.index())
    tile = again.get_tile((0, 0))
    assert tile is not None and tile.version == version and not tile.dirty
    again.fuse("a", full(100), block(0, 0), stamp=2.0)
    assert again.tiles[(0, 0)].version > version  # the clock moved past the loaded one
    restarted.close()


def test_the_version_travels_in_the_tile_header_and_is_checked() -> None:
    expect = Expectation("test", RES, T, "map")
    data = np.zeros((1, T, T), np.int16)
    blob = tile_to_bytes(tile_header(expect, 2, -1, ["a"], 3.0, version=123456789), data)
    assert tile_from_bytes(blob, expect).header.tile_version == 123456789
    assert b"tile_version" not in tile_to_bytes(tile_header(expect, 2, -1, ["a"], 3.0), data)
    assert tile_from_bytes(tile_to_bytes(tile_header(expect, 0, 0, ["a"], 0.0), data)
                           ).header.tile_version == 0
    for bad in (-1, True, 1.5, "7", 1 << 63):
        with pytest.raises(TileFormatError, match="tile_version"):
            tilefile._version_field({"tile_version": bad})
