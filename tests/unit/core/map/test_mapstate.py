"""Dropping layers from the map state (MapState.drop_layers): planes, bytes, versions, tiles
left empty, retired layer indices, and tiles loaded back while a drop runs."""

from __future__ import annotations

import sys
import threading
import time

import numpy as np

from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice
from sogm_service.core.map.tiles import TiledMap

RES, T = 0.5, 8


def fused_map() -> TiledMap:
    """robot1 in tiles (0,0), (1,0); robot2 in (1,0), (2,0): (2,0) holds robot2 alone."""
    m = TiledMap("test", "map", TileLattice(RES, T))
    inc = np.full((T, 2 * T), 700, np.int16)
    m.fuse("robot1/laser", inc, GridGeometry(RES, 2 * T, T, Pose2D(0.0, 0.0, 0.0)), "nearest")
    m.fuse("robot2/laser", inc, GridGeometry(RES, 2 * T, T, Pose2D(T * RES, 0.0, 0.0)),
           "nearest")
    return m


def window(m: TiledMap, layers: list[str]) -> np.ndarray:
    geometry = GridGeometry(RES, 3 * T, T, Pose2D(0.0, 0.0, 0.0))
    return m.sample(geometry, layers, "nearest")


def test_drop_removes_planes_and_empty_tiles_and_leaves_the_rest_bit_for_bit() -> None:
    m = fused_map()
    before = window(m, ["robot1/laser"])
    versions = {i: t.version for i, t in m.tiles.items()}
    gone, rewritten, emptied = m.drop_layers(["robot2/laser", "nobody/laser"])
    assert gone == ["robot2/laser"]
    assert sorted(rewritten) == [(1, 0), (2, 0)] and emptied == [(2, 0)]
    assert m.layers == ["robot1/laser"]
    assert sorted(m.tiles) == [(0, 0), (1, 0)] and (2, 0) not in m.known_tiles()
    assert m.tiles[(1, 0)].version > versions[(1, 0)]  # dirty: the caller stores it
    assert m.tiles[(0, 0)].version == versions[(0, 0)]
    assert m.resident_bytes() == 2 * T * T * 2  # one plane in each of two tiles
    assert np.array_equal(window(m, ["robot1/laser"]), before)
    # A read that named the layer just before the drop reads it as unknown (no KeyError).
    assert not window(m, ["robot2/laser"]).any()
    snap = m.snapshot((1, 0))
    assert snap is not None and snap.layers == ["robot1/laser"]
    names, stack = m.tile_layers(m.tiles[(1, 0)])
    assert names == ["robot1/laser"] and stack.shape == (1, T, T) and stack.min() == 700


def test_a_dropped_index_is_never_reused() -> None:
    m = fused_map()
    old = m.layer_id("robot2/laser")
    m.drop_layers(["robot2/laser"])
    tile = m.tiles[(1, 0)]
    with tile.lock:  # a fuse that got the index before the drop adds into a plane not kept
        m._plane(tile, old)[:] = 5
    assert old not in tile.planes
    new = m.layer_id("robot2/laser", create=True)  # the name again: a new, empty layer
    assert new != old
    assert not window(m, ["robot2/laser"]).any()


def test_tiles_loaded_during_a_drop_leave_the_layers_out_and_come_back_dirty() -> None:
    stack = np.stack([np.full((T, T), 300, np.int16), np.full((T, T), -400, np.int16)])
    m = TiledMap("test", "map", TileLattice(RES, T),
                 loader=lambda i, j: (["robot1/laser", "robot2/laser"], stack.copy(), 1.0))
    m.stored = {(0, 0), (1, 0)}
    m.adopt_layers(["robot1/laser", "robot2/laser"])
    m.drop_layers(["robot2/laser"])
    tile = m.get_tile((0, 0))
    assert tile is not None and tile.dirty and len(tile.planes) == 1
    assert int(next(iter(tile.planes.values())).min()) == 300  # robot1's plane
    assert m.layers == ["robot1/laser"]  # the load did not bring the layer back
    m.end_drop()
    again = m.get_tile((1, 0))
    assert again is not None and not again.dirty and sorted(m.layers) == [
        "robot1/laser", "robot2/laser"]


def test_drops_racing_fuses_leave_no_orphan_planes_and_robot1_intact() -> None:
    """robot2's ISMs fused on another thread while its layer is dropped again and again: every
    plane a tile keeps belongs to a live layer, the byte count stays exact, robot1 unchanged."""
    m = fused_map()
    before = window(m, ["robot1/laser"])
    inc = np.full((T, 64 * T), 300, np.int16)  # 64 tiles: a long second phase to land in
    geometry = GridGeometry(RES, 64 * T, T, Pose2D(T * RES, 0.0, 0.0))
    stop = threading.Event()

    def fuse_robot2() -> None:
        while not stop.is_set():
            m.fuse("robot2/laser", inc, geometry, "nearest")

    worker = threading.Thread(target=fuse_robot2)
    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # threads switch often: drops land inside fuses
    worker.start()
    try:
        for _ in range(50):
            m.drop_layers(["robot2/laser"])
            deadline = time.monotonic() + 5.0
            while "robot2/laser" not in m.layers and time.monotonic() < deadline:
                time.sleep(0.0005)  # the fuses start the layer again
    finally:
        stop.set()
        worker.join(10)
        sys.setswitchinterval(interval)
    names = m._names
    assert all(names[lid] is not None for t in m.tiles.values() for lid in t.planes)
    assert m.resident_bytes() == sum(t.nbytes for t in m.tiles.values())
    assert np.array_equal(window(m, ["robot1/laser"]), before)
    assert len(names) == 1 + 51  # robot1's, then robot2's started again 50 times


def test_a_snapshot_saved_after_its_tile_left_does_not_bring_it_back() -> None:
    """The writer confirms a snapshot taken before the drop emptied the tile (or before a
    discard): the map does not count the tile as stored again (the caller removes the file)."""
    m = fused_map()
    version = m.tiles[(2, 0)].version
    m.drop_layers(["robot2/laser"])  # (2, 0) held robot2 alone
    m.mark_saved((2, 0), version)
    assert (2, 0) not in m.known_tiles()
    m.discard((0, 0))
    m.mark_saved((0, 0), 1)
    assert (0, 0) not in m.known_tiles()
    m.mark_saved((1, 0), m.tiles[(1, 0)].version)  # a resident tile: stored and clean
    assert (1, 0) in m.stored and not m.tiles[(1, 0)].dirty
