"""Tiles keep one plane per layer written (adding a layer copies nothing) and a fuse is
transactional: if it fails half-way no tile has changed."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

import sogm_service.core.map.fusing as fusing_module
from sogm_service.core import resample
from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice
from sogm_service.core.map.tile import TileSnapshot
from sogm_service.core.map.tiles import TiledMap

RES, T = 0.05, 16
SPAN = RES * T
PLANE = T * T * 2  # bytes of one (T, T) int16 plane

Stored = dict[tuple[int, int], tuple[list[str], np.ndarray, float]]


def new_map(loader: Any = None) -> TiledMap:
    return TiledMap("test", "map", TileLattice(RES, T), loader=loader)


def block(i: int, j: int, w: int = 4, h: int = 4) -> GridGeometry:
    """An aligned ISM of ``w x h`` cells inside tile ``(i, j)``."""
    return GridGeometry(RES, w, h, Pose2D(i * SPAN + 2 * RES, j * SPAN + 2 * RES, 0.0))


def ones(value: int, w: int = 4, h: int = 4) -> np.ndarray:
    return np.full((h, w), value, np.int16)


def truth(m: TiledMap) -> int:
    """Resident bytes counted from scratch: every resident tile's planes."""
    return sum(int(p.nbytes) for t in m.resident() for p in t.planes.values())


def state(m: TiledMap) -> dict[str, Any]:
    """Everything a failed fuse must leave as it was."""
    snaps: dict[tuple[int, int], TileSnapshot | None] = {
        index: m.snapshot(index) for index in sorted(m.tiles)}
    return {
        "layers": list(m.layers), "now": m.now(), "known": m.known_tiles(),
        "stored": set(m.stored), "resident": set(m.tiles), "bytes": m.resident_bytes(),
        "tiles": {index: None if s is None else
                  (s.layers, s.data.tobytes(), s.stamp, s.version, s.dirty, s.decay, s.applied)
                  for index, s in snaps.items()},
        "saved": {index: t.saved_version for index, t in m.tiles.items()},
        "planes": {index: sorted(t.planes) for index, t in m.tiles.items()},
    }


def assert_unpinned(m: TiledMap) -> None:
    assert all(t.pins == 0 for t in m.resident())


# -- planes -------------------------------------------------------------------------------
def test_adding_a_layer_keeps_the_other_planes_as_the_same_objects() -> None:
    m = new_map()
    m.fuse("a", ones(300), block(0, 0))
    tile = m.tiles[(0, 0)]
    plane_a = tile.planes[0]
    before = plane_a.copy()
    for k in range(1, 20):
        m.fuse(f"layer{k}", ones(100 + k), block(0, 0))
        assert tile.planes[0] is plane_a  # not copied, not reallocated
    np.testing.assert_array_equal(plane_a, before)
    assert sorted(tile.planes) == list(range(20))
    assert tile.nbytes == 20 * PLANE == m.resident_bytes()
    # every layer reads back what was written into it
    got = m.sample(block(0, 0), m.layers)
    assert [int(got[k, 0, 0]) for k in range(20)] == [300] + [100 + k for k in range(1, 20)]


def test_a_tile_written_in_one_of_1000_layers_holds_one_plane() -> None:
    m = new_map()
    for k in range(999):
        m.fuse(f"l{k:04d}", ones(50), block(0, 0, 1, 1))
    m.fuse("l0999", ones(70), block(3, 0))
    lone = m.tiles[(3, 0)]
    assert list(lone.planes) == [999] and lone.nbytes == PLANE
    assert m.tiles[(0, 0)].nbytes == 999 * PLANE
    assert m.resident_bytes() == truth(m) == 1000 * PLANE
    snap = m.snapshot((3, 0))  # sparse: the one layer this tile has, not 1,000 planes
    assert snap is not None and snap.layers == ["l0999"] and snap.data.shape == (1, T, T)
    assert (snap.data[0, 2:6, 2:6] == 70).all()
    names, stack = m.tile_layers(lone)  # the full stack in the map's layer order
    assert names == m.layers and stack.shape == (1000, T, T)
    assert not stack[:999].any() and np.array_equal(stack[999], snap.data[0])


def test_1000_new_layers_on_the_same_4_tiles_cost_memory_linear_in_planes_written() -> None:
    """1,000 tiny ISMs, each a new layer, on the 4 tiles around one corner: memory grows with
    the planes written, never with a copy of every tile's whole stack."""
    m = new_map()
    corner = GridGeometry(RES, 2, 2, Pose2D(SPAN - RES, SPAN - RES, 0.0))
    quad = {(0, 0), (1, 0), (0, 1), (1, 1)}
    first: dict[tuple[int, int], np.ndarray] = {}
    for k in range(1000):
        assert set(m.fuse(f"layer{k:04d}", ones(k + 1, 2, 2), corner, stamp=float(k))) == quad
        if k == 0:
            first = {index: m.tiles[index].planes[0] for index in quad}
        assert m.resident_bytes() == 4 * (k + 1) * PLANE  # linear: one plane per tile written
    assert set(m.tiles) == quad and len(m.layers) == 1000
    for index in quad:
        assert m.tiles[index].planes[0] is first[index]  # never copied
        assert len(m.tiles[index].planes) == 1000
    assert m.resident_bytes() == truth(m)
    got = m.sample(corner, m.layers)
    assert all((got[k] == k + 1).all() for k in range(1000))


def test_the_resident_byte_count_is_the_sum_of_resident_planes_after_mixed_operations() -> None:
    stored: Stored = {}
    m = new_map(loader=lambda i, j: stored.get((i, j)))

    def keep(s: TileSnapshot) -> None:
        stored[s.index] = (s.layers, s.data, s.stamp)

    rng = np.random.default_rng(5)
    steps = 0
    for k in range(60):
        op = int(rng.integers(0, 6))
        i, j = (int(v) for v in rng.integers(-2, 3, 2))
        if op <= 1:  # fuse, sometimes rotated, sometimes a new layer
            yaw = 0.0 if op == 0 else 0.4
            m.fuse(f"l{int(rng.integers(0, 8))}", ones(int(rng.integers(-900, 900)) or 1, 20, 20),
                   GridGeometry(RES, 20, 20, Pose2D(i * SPAN, j * SPAN, yaw)), stamp=float(k))
        elif op == 2 and m.tiles:
            m.evict(sorted(m.tiles)[int(rng.integers(0, len(m.tiles)))], before=keep)
        elif op == 3 and m.stored:
            m.get_tile(sorted(m.stored)[0])  # loaded back
        elif op == 4:  # a replica's tile, one of its layers all unknown: no plane for it
            stack = np.zeros((3, T, T), np.int16)
            stack[0, 0, 0], stack[2, 5, 5] = 11, -22
            m.insert_tile((i, j), ["a", "zero", "b"], stack, 1.0, saved=False)
            assert len(m.tiles[(i, j)].planes) == 2
        elif op == 5:
            m.discard((i, j))
        assert m.resident_bytes() == truth(m)
        steps += 1
    assert steps == 60 and m.resident_bytes() > 0


def test_inserted_and_loaded_stacks_keep_all_zero_layers_absent() -> None:
    stack = np.zeros((3, T, T), np.int16)
    stack[0, 1, 1] = 500
    stack[2, 2, 2] = -400
    m = new_map(loader=lambda i, j: (["x", "empty", "y"], stack.copy(), 2.0))
    m.stored.add((5, 5))
    loaded = m.get_tile((5, 5))
    assert loaded is not None and loaded.nbytes == 2 * PLANE
    assert sorted(m.layers[k] for k in loaded.planes) == ["x", "y"]
    tile = m.insert_tile((0, 0), ["x", "empty", "y"], stack, 1.0, saved=True)
    assert tile.nbytes == 2 * PLANE
    snap = m.snapshot((0, 0))
    assert snap is not None and snap.layers == ["x", "y"]  # the all-zero layer stays absent
    np.testing.assert_array_equal(snap.data, stack[[0, 2]])
    assert m.resident_bytes() == truth(m) == 4 * PLANE


# -- a failed fuse changes nothing ----------------------------------------------------------
def footprint_map(fail: tuple[int, int] | None) -> tuple[TiledMap, Stored]:
    """Tiles of a 3x3 footprint at (0..2, 0..2): (0, 0) and (1, 1) stored (evicted), (0, 1)
    and (2, 1) resident, the rest absent.  The loader raises for ``fail``."""
    stored: Stored = {}

    def loader(i: int, j: int) -> tuple[list[str], np.ndarray, float] | None:
        if (i, j) == fail:
            raise OSError(f"disk error reading tile {(i, j)}")
        got = stored.get((i, j))
        return None if got is None else (list(got[0]), got[1].copy(), got[2])

    m = new_map(loader=loader)
    m.set_forget({"decaying": 30.0})
    for index in [(0, 0), (1, 1), (0, 1), (2, 1)]:
        m.fuse("a", ones(400), block(*index), stamp=1.0)
        m.fuse("decaying", ones(-600), block(*index), stamp=2.0, mark=("robot", (2.0, 7)))
    for index in [(0, 0), (1, 1)]:
        m.evict(index, before=lambda s: stored.__setitem__(s.index, (s.layers, s.data,
                                                                      s.stamp)))
    assert set(m.tiles) == {(0, 1), (2, 1)} and m.stored == {(0, 0), (1, 1)}
    return m, stored


def whole_footprint() -> tuple[np.ndarray, GridGeometry]:
    inc = np.full((3 * T, 3 * T), 250, np.int16)
    return inc, GridGeometry(RES, 3 * T, 3 * T, Pose2D(0.0, 0.0, 0.0))


def test_a_loader_failing_in_the_middle_of_a_footprint_leaves_the_map_bit_identical() -> None:
    m, _ = footprint_map(fail=(1, 1))
    before = state(m)
    inc, geom = whole_footprint()
    # raster order: (0, 0) loaded back, (1, 0) and (2, 0) created, (0, 1) resident, then (1, 1)
    with pytest.raises(OSError, match="disk error"):
        m.fuse("a", inc, geom, stamp=5.0, mark=("robot", (5.0, 9)))
    assert state(m) == before
    assert m.resident_bytes() == truth(m)
    assert_unpinned(m)
    # and the map still works: the same ISM rotated off the failing tile fuses, evicts, loads
    touched = m.fuse("a", inc[:T, :], GridGeometry(RES, 3 * T, T, Pose2D(0.0, 0.0, 0.0)),
                     stamp=5.0)
    assert sorted(touched) == [(0, 0), (1, 0), (2, 0)]
    assert m.evict((0, 0)) is not None


@pytest.mark.parametrize("yaw", [0.0, 0.3])
def test_a_patch_failing_half_way_leaves_the_map_unchanged_and_creates_no_tile(
        monkeypatch: pytest.MonkeyPatch, yaw: float) -> None:
    m, _ = footprint_map(fail=None)
    m.get_tile((0, 0))  # one stored tile resident again, one still stored
    before = state(m)
    real = resample.tile_patches
    yielded: list[tuple[int, int]] = []

    def failing(*args: Any, **kw: Any) -> Iterator[resample.TilePatch]:
        for k, part in enumerate(real(*args, **kw)):
            if k == 5:
                raise RuntimeError("resampling failed")
            yielded.append(part.index)
            yield part

    monkeypatch.setattr(fusing_module, "tile_patches", failing)
    inc, _ = whole_footprint()
    geom = GridGeometry(RES, 3 * T, 3 * T, Pose2D(0.3, 0.1, yaw))
    with pytest.raises(RuntimeError, match="resampling failed"):
        m.fuse("new_layer", inc, geom, stamp=9.0)
    assert len(yielded) == 5 and set(yielded) - set(before["resident"])  # would create tiles
    assert state(m) == before  # no new tile, no new layer, the clock where it was
    assert_unpinned(m)


def test_running_out_of_memory_for_a_plane_rolls_back_the_tiles_created_and_loaded(
        monkeypatch: pytest.MonkeyPatch) -> None:
    m, _ = footprint_map(fail=None)
    before = state(m)
    calls = []
    real = m._new_plane

    def short_of_memory() -> np.ndarray:
        calls.append(1)
        if len(calls) == 4:
            raise MemoryError
        return real()

    monkeypatch.setattr(m, "_new_plane", short_of_memory)
    inc, geom = whole_footprint()
    with pytest.raises(MemoryError):
        m.fuse("b", inc, geom, stamp=5.0)  # a new layer: every tile needs a plane
    assert len(calls) == 4
    assert state(m) == before
    assert_unpinned(m)


def test_a_successful_fuse_after_a_failed_one_matches_a_map_that_never_saw_it() -> None:
    failing, stored = footprint_map(fail=(1, 1))
    clean, _ = footprint_map(fail=None)
    inc, geom = whole_footprint()
    with pytest.raises(OSError):
        failing.fuse("a", inc, geom, stamp=5.0)
    failing.loader = lambda i, j: stored.get((i, j))  # the disk is back
    for m in (failing, clean):
        m.fuse("a", inc, geom, stamp=6.0)
    window = GridGeometry(RES, 4 * T, 4 * T, Pose2D(-SPAN / 2, -SPAN / 2, 0.0))
    np.testing.assert_array_equal(failing.sample(window, ["a", "decaying"]),
                                  clean.sample(window, ["a", "decaying"]))
    assert failing.known_tiles() == clean.known_tiles()


# -- the tiles of a fuse in progress ---------------------------------------------------------
def test_a_tile_pinned_by_a_fuse_in_progress_is_not_evicted() -> None:
    """Between the phases of a fuse its tiles cannot be evicted (phase 2 would have to load
    them back, which may fail after other tiles were written)."""
    m, _ = footprint_map(fail=None)
    evictions: list[object] = []
    plain = m.loader
    assert plain is not None

    def loader_that_evicts(i: int, j: int) -> Any:
        if (i, j) == (1, 1):  # (0, 0), (1, 0), (2, 0), (0, 1) are pinned by now
            evictions.append(m.evict((0, 1)))
        return plain(i, j)

    m.loader = loader_that_evicts
    inc, geom = whole_footprint()
    m.fuse("a", inc, geom, stamp=5.0)
    assert evictions == [None] and (0, 1) in m.tiles
    assert int(m.sample(block(0, 1), ["a"])[0, 0, 0]) == 650  # 400 + 250, in the map's tile
    assert_unpinned(m)
    assert m.evict((0, 1)) is not None  # released afterwards


@pytest.mark.parametrize("how", ["insert", "discard"])
def test_a_tile_replaced_or_discarded_between_the_phases_gets_the_patch(how: str) -> None:
    """A cluster handover may replace (insert_tile) or drop (discard) a tile meanwhile: the
    patch goes to the map's tile of phase 2, never to the one that left."""
    m, _ = footprint_map(fail=None)
    plain = m.loader
    assert plain is not None
    left = m.tiles[(0, 1)]

    def loader(i: int, j: int) -> Any:
        if (i, j) == (1, 1):
            if how == "insert":
                stack = np.full((1, T, T), 1000, np.int16)
                m.insert_tile((0, 1), ["a"], stack, 3.0, saved=True)
            else:
                m.discard((0, 1))
        return plain(i, j)

    m.loader = loader
    inc, geom = whole_footprint()
    before_left = m.tile_layers(left)[1]
    m.fuse("a", inc, geom, stamp=5.0)
    assert m.tiles[(0, 1)] is not left and left.evicted
    np.testing.assert_array_equal(m.tile_layers(left)[1], before_left)  # untouched
    want = 1250 if how == "insert" else 250
    assert (m.sample(GridGeometry(RES, T, T, Pose2D(0.0, SPAN, 0.0)), ["a"]) == want).all()
    assert m.resident_bytes() == truth(m)
    assert_unpinned(m)
