"""The tiled map (tiles.py): ISMs fused into lattice tiles (Eq. 1) and windows sampled back.

Expected placements are computed by hand from the lattice definition of the architecture page,
section 4 (docs/architecture.md#4-maps-and-tiles)
(tile ``(i, j)`` covers ``[i T r, (i + 1) T r) x [j T r, (j + 1) T r)``), never from the
module's own geometry helpers.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice, window_geometry
from sogm_service.core.map.tiles import TiledMap
from tests.oracles import sample_bilinear
from tests.unit.core.test_logodds import HI

RES = 0.1
T = 8  # small tiles so that small ISMs cross boundaries


def new_map(eps0: float = 0.001, **kw: object) -> TiledMap:
    return TiledMap("test", "map", TileLattice(RES, T), eps0=eps0, **kw)  # type: ignore[arg-type]


def random_increments(rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
    inc = rng.integers(-logodds.MAX_STATE, logodds.MAX_STATE + 1, shape).astype(np.int16)
    inc[rng.random(shape) < 0.2] = 0  # some unknown cells
    return inc


def cell_value(m: TiledMap, layer: str, col: int, row: int) -> int:
    """A map cell (global cell index) read straight from its tile; 0 if there is no tile."""
    tile = m.tiles.get((col // T, row // T))
    lid = m.layers.index(layer)
    plane = None if tile is None else tile.planes.get(lid)
    if plane is None:
        return 0
    return int(plane[row % T, col % T])


def test_aligned_ism_samples_back_as_its_clamped_increments() -> None:
    rng = np.random.default_rng(1)
    m = new_map()
    lo, hi = m.limits
    inc = random_increments(rng, (7, 10))
    geom = GridGeometry(RES, 10, 7, Pose2D(3 * RES, 2 * RES, 0.0))  # inside tile (0, 0)+
    m.fuse("obstacle", inc, geom)
    for interp in ("biodds", "bilinear", "nearest"):  # aligned: no interpolation at all
        got = m.sample(geom, ["obstacle"], interp)
        assert got.shape == (1, 7, 10) and got.dtype == np.int16
        np.testing.assert_array_equal(got[0], np.clip(inc, lo, hi))
    m.fuse("obstacle", inc, geom)  # Eq. 1 again: the sum, clamped
    np.testing.assert_array_equal(m.sample(geom, ["obstacle"])[0],
                                  np.clip(np.clip(inc, lo, hi) + inc.astype(np.int64), lo, hi))


def test_ism_across_tile_boundaries_lands_in_every_tile() -> None:
    rng = np.random.default_rng(2)
    m = new_map()
    lo, hi = m.limits
    inc = random_increments(rng, (19, 21))
    inc[0, 0] = inc[-1, -1] = 5000  # the corner cells must land too
    c0, r0 = -5, -3  # the ISM's corner cell in global map cells
    geom = GridGeometry(RES, 21, 19, Pose2D(c0 * RES, r0 * RES, 0.0))
    touched = m.fuse("obstacle", inc, geom)
    expected_tiles = {(i, j) for i in range(math.floor(c0 / T), math.floor((c0 + 20) / T) + 1)
                      for j in range(math.floor(r0 / T), math.floor((r0 + 18) / T) + 1)}
    # cells -5..15 x -3..15 -> tiles -1..1 x -1..1
    assert set(touched) == expected_tiles == {(i, j) for i in (-1, 0, 1) for j in (-1, 0, 1)}
    assert set(m.tiles) == expected_tiles
    for v in range(19):
        for u in range(21):
            assert cell_value(m, "obstacle", c0 + u, r0 + v) == np.clip(inc[v, u], lo, hi)
    # nothing outside the ISM was written
    for tile in m.tiles.values():
        assert np.count_nonzero(m.tile_layers(tile)[1]) <= np.count_nonzero(inc)
    assert sum(np.count_nonzero(m.tile_layers(t)[1]) for t in m.tiles.values()) \
        == np.count_nonzero(inc)
    # a window across all the tiles reads it back, with unknown around it
    window = GridGeometry(RES, 25, 23, Pose2D((c0 - 2) * RES, (r0 - 2) * RES, 0.0))
    got = m.sample(window, ["obstacle"])[0]
    np.testing.assert_array_equal(got[2:21, 2:23], np.clip(inc, lo, hi))
    got[2:21, 2:23] = 0
    assert not got.any()


def test_window_from_centre_pose_across_tiles() -> None:
    m = new_map()
    inc = np.full((16, 16), 700, np.int16)
    m.fuse("a", inc, GridGeometry(RES, 16, 16, Pose2D(-0.8, -0.8, 0.0)))
    w = window_geometry(0.0, 0.0, 0.0, 1.2, 1.2, RES)  # centred on the corner of 4 tiles
    got = m.sample(w, ["a"])[0]
    assert got.shape == (12, 12) and (got == 700).all()


@pytest.mark.parametrize("yaw,ism_res", [(0.5, 0.2), (math.pi / 2 + 0.1, 0.25), (-2.0, 0.13)])
def test_rotated_rescaled_ism_lands_where_geometry_says(yaw: float, ism_res: float) -> None:
    m = new_map()
    inc = np.zeros((5, 6), np.int16)
    inc[2, 3] = 3000  # one marked ISM cell, everything else unknown
    origin = Pose2D(0.37, -0.21, yaw)
    m.fuse("a", inc, GridGeometry(ism_res, 6, 5, origin), interp="nearest")
    c, s = math.cos(yaw), math.sin(yaw)
    marked = 0
    for col in range(-30, 30):
        for row in range(-30, 30):
            # the map cell centre, in the ISM's frame, in ISM cells
            x, y = (col + 0.5) * RES - origin.x, (row + 0.5) * RES - origin.y
            iu, iv = (c * x + s * y) / ism_res, (-s * x + c * y) / ism_res
            inside = math.floor(iu) == 3 and math.floor(iv) == 2
            near_edge = min(abs(iu - round(iu)), abs(iv - round(iv))) < 1 / 16
            value = cell_value(m, "a", col, row)
            if not near_edge:  # OpenCV rounds positions to 1/32 cell
                assert value == (3000 if inside else 0), (col, row)
            marked += value == 3000
    # about (ism_res / RES)^2 map cells hold the one ISM cell
    assert abs(marked - (ism_res / RES) ** 2) <= 2 * ism_res / RES + 2


def test_rotated_ism_with_biodds_peaks_at_the_marked_cell() -> None:
    m = new_map()
    inc = np.zeros((6, 6), np.int16)
    inc[1, 4] = 4000
    origin = Pose2D(-0.3, 0.4, 1.0)
    m.fuse("a", inc, GridGeometry(0.2, 6, 6, origin))  # biodds: bilinear in log-odds
    centre = np.array([origin.x, origin.y]) + np.array(
        [[math.cos(1.0), -math.sin(1.0)], [math.sin(1.0), math.cos(1.0)]]) @ [0.9, 0.3]
    best = max((cell_value(m, "a", c, r), c, r) for c in range(-20, 20)
                for r in range(-20, 20))
    assert 0 < best[0] <= 4000
    peak = np.array([(best[1] + 0.5) * RES, (best[2] + 0.5) * RES])
    assert np.linalg.norm(peak - centre) <= RES * math.sqrt(0.5) + 1e-9
    # unknown around stays unknown
    assert all(m.tile_layers(t)[1].min() >= 0 for t in m.tiles.values())


def test_unknown_area_samples_as_zero() -> None:
    m = new_map()
    far = GridGeometry(RES, 5, 5, Pose2D(100.0, 100.0, 0.3))
    m.fuse("a", np.full((4, 4), 900, np.int16), GridGeometry(RES, 4, 4))
    assert (m.sample(far, ["a"]) == 0).all()
    assert (m.sample(far, ["a"], "bilinear") == 0).all()
    # a layer that a tile predates reads as unknown there
    m.fuse("b", np.full((2, 2), 500, np.int16), GridGeometry(RES, 2, 2, Pose2D(5.0, 5.0)))
    got = m.sample(GridGeometry(RES, 4, 4), ["a", "b"])
    assert (got[0] == 900).all() and (got[1] == 0).all()
    with pytest.raises(KeyError):
        m.sample(far, ["no-such-layer"])


def test_layers_are_created_on_their_first_ism() -> None:
    m = new_map()
    assert m.layers == []
    geom = GridGeometry(RES, 3, 3)
    m.fuse("floor", np.full((3, 3), -800, np.int16), geom)
    assert m.layers == ["floor"]
    m.fuse("table", np.full((3, 3), 600, np.int16), geom)
    m.fuse("floor", np.full((3, 3), -100, np.int16), geom)
    assert m.layers == ["floor", "table"]
    assert sorted(m.tiles[(0, 0)].planes) == [0, 1]  # one (T, T) plane per layer written
    assert m.tile_layers(m.tiles[(0, 0)])[1].shape == (2, T, T)
    got = m.sample(geom, ["table", "floor"])
    assert (got[0] == 600).all() and (got[1] == -900).all()


def test_all_unknown_ism_creates_no_tile() -> None:
    m = new_map()
    zeros = np.zeros((20, 20), np.int16)
    assert m.fuse("a", zeros, GridGeometry(RES, 20, 20, Pose2D(-1.0, -1.0, 0.4))) == []
    assert m.tiles == {} and m.bounds() is None
    # an ISM known only in one tile creates only that tile
    inc = zeros.copy()
    inc[:2, :2] = 300  # global cells -10..-9 -> tile (-2, -2) (cells -16..-9)
    m.fuse("a", inc, GridGeometry(RES, 20, 20, Pose2D(-1.0, -1.0, 0.0)))
    assert set(m.tiles) == {(-2, -2)}


@pytest.mark.parametrize("eps0", [logodds.MIN_EPS0, 0.001, 0.2])
def test_clamp_holds_after_repeated_fusion(eps0: float) -> None:
    rng = np.random.default_rng(7)
    m = new_map(eps0)
    lo, hi = m.limits
    geom = GridGeometry(RES, 12, 12, Pose2D(-0.55, -0.35, 0.3))  # rotated: resampled path
    for k in range(25):
        inc = np.full((12, 12), logodds.MAX_STATE if k % 2 == 0 else -logodds.MAX_STATE,
                      np.int16)
        inc[rng.random((12, 12)) < 0.5] = logodds.MAX_STATE
        m.fuse("a", inc, geom)
        m.fuse("a", inc, GridGeometry(RES, 12, 12, Pose2D(0.2, 0.1, 0.0)))  # aligned path
        for tile in m.tiles.values():
            stack = m.tile_layers(tile)[1]
            assert stack.min() >= lo and stack.max() <= hi
    assert max(int(m.tile_layers(t)[1].max()) for t in m.tiles.values()) == hi


def test_tiles_loaded_back_are_clamped_to_this_map() -> None:
    # A stored tile written under a wider clamp (or damaged) must not break Eq. 1's invariant.
    stored = np.zeros((1, T, T), np.int16)
    stored[0, 0, 0] = 32767
    stored[0, 0, 1] = -32768
    stored[0, 0, 2] = 15000
    m = new_map(0.01, loader=lambda i, j: (["a"], stored.copy(), 1.0))
    m.stored.add((0, 0))
    lo, hi = m.limits
    tile = m.get_tile((0, 0))
    assert tile is not None
    stack = m.tile_layers(tile)[1]
    assert stack.min() >= lo and stack.max() <= hi
    m.fuse("a", np.full((1, 3), logodds.MAX_STATE, np.int16), GridGeometry(RES, 3, 1))
    np.testing.assert_array_equal(m.sample(GridGeometry(RES, 3, 1), ["a"])[0, 0], [hi, hi, hi])


def test_evicted_tiles_come_back_through_the_loader() -> None:
    saved: dict[tuple[int, int], tuple[list[str], np.ndarray, float]] = {}
    m = new_map(loader=lambda i, j: saved.get((i, j)))
    inc = np.arange(16, dtype=np.int16).reshape(4, 4) * 100
    geom = GridGeometry(RES, 4, 4, Pose2D(-0.2, -0.2, 0.0))
    m.fuse("a", inc, geom, stamp=3.0)
    for index in list(m.tiles):
        names, stack = m.tile_layers(m.tiles[index])
        saved[index] = (names, stack.copy(), 3.0)
        m.evict(index)
    assert m.tiles == {} and m.known_tiles() == set(saved)
    np.testing.assert_array_equal(m.sample(geom, ["a"])[0], inc)
    assert set(m.tiles) == set(saved)


def test_reading_a_tile_makes_it_recently_used() -> None:
    m = new_map()
    m.fuse("a", np.full((2, 2), 100, np.int16), GridGeometry(RES, 2, 2))  # tile (0, 0)
    m.fuse("a", np.full((2, 2), 100, np.int16), GridGeometry(RES, 2, 2, Pose2D(1.0, 0.0)))
    assert m.least_recently_used() == [(0, 0), (1, 0)]
    m.sample(GridGeometry(RES, 2, 2), ["a"])  # reads tile (0, 0) only
    assert m.least_recently_used() == [(1, 0), (0, 0)]


def test_insert_tile_clamps_and_adopts_layers() -> None:
    m = new_map()
    lo, hi = m.limits
    stack = np.full((2, T, T), 30000, np.int16)
    stack[1] = -30000
    m.insert_tile((3, -1), ["x", "y"], stack, stamp=2.0, saved=True)
    assert m.layers == ["x", "y"]
    got = m.sample(GridGeometry(RES, T, T, Pose2D(3 * T * RES, -T * RES, 0.0)), ["y", "x"])
    assert (got[0] == lo).all() and (got[1] == hi).all()
    with pytest.raises(ValueError):
        m.insert_tile((0, 0), ["x"], np.zeros((1, T, T + 1), np.int16), 0.0, False)


@pytest.mark.parametrize("interp", ["nearest", "biodds"])
def test_tiles_behave_like_one_big_grid(interp: str) -> None:
    """Fusing tile by tile equals sampling the ISM once at every map cell centre: an exact
    reference (numpy, float64), within OpenCV's 1/32-cell position rounding."""
    rng = np.random.default_rng(11)
    m = new_map()
    lo, hi = m.limits
    inc = rng.integers(-3000, 3001, (15, 17)).astype(np.int16)
    ism = GridGeometry(0.13, 17, 15, Pose2D(-0.71, -0.43, 0.7))
    m.fuse("a", inc, ism, interp)
    big = GridGeometry(RES, 60, 60, Pose2D(-3.2, -3.2, 0.0))
    got = m.sample(big, ["a"])[0].astype(np.int64)
    # ISM cell coordinates of every big-grid cell centre, by hand
    c, s = math.cos(0.7), math.sin(0.7)
    x = -3.2 + (np.arange(60)[None, :] + 0.5) * RES + 0.71
    y = -3.2 + (np.arange(60)[:, None] + 0.5) * RES + 0.43
    su = (c * x + s * y) / 0.13 - 0.5
    sv = (-s * x + c * y) / 0.13 - 0.5
    inside = (su > -0.5) & (su < 16.5) & (sv > -0.5) & (sv < 14.5)  # within the ISM's area
    beyond = (su < -1) | (su > 17) | (sv < -1) | (sv > 15)  # past every interpolation reach
    assert inside.sum() > 300 and beyond.sum() > 2000
    assert not got[beyond].any()
    if interp == "nearest":
        ref = inc[np.clip(np.floor(sv + 0.5), 0, 14).astype(int),
                  np.clip(np.floor(su + 0.5), 0, 16).astype(int)]
        near_tie = (np.abs(su - np.floor(su) - 0.5) < 1 / 32) | (
            np.abs(sv - np.floor(sv) - 0.5) < 1 / 32)
        ok = inside & ~near_tie
        np.testing.assert_array_equal(got[ok], np.clip(ref[ok], lo, hi))
    else:
        ref = np.clip(np.rint(sample_bilinear(inc, su, sv, 0.0)), lo, hi)
        # half a unit of rounding; a neighbour spread of at most 6000 units times 1/64 cell
        # of position rounding on each axis
        assert np.abs(got[inside] - ref[inside]).max() <= 1 + 6000 * 2 / 64


def test_lattice_tile_of_matches_the_tile_areas() -> None:
    lattice = TileLattice(0.05, 256)
    span = 256 * 0.05
    rng = np.random.default_rng(12)
    for x, y in rng.uniform(-100, 100, (200, 2)):
        i, j = lattice.tile_of(x, y)
        assert i * span <= x < (i + 1) * span and j * span <= y < (j + 1) * span
        u, v = lattice.tile_geometry(i, j).world_to_index([x, y])
        assert 0 <= u < 256 and 0 <= v < 256
    assert lattice.tile_of(-1e-9, 0.0) == (-1, 0)
    with pytest.raises(ValueError):
        TileLattice(0.05, 100)  # not a power of two


def test_window_geometry_is_centred_on_its_pose() -> None:
    for yaw in (0.0, 0.4, -2.5):
        w = window_geometry(1.5, -2.0, yaw, 3.0, 2.0, 0.1)
        assert (w.width, w.height) == (30, 20)
        centre = w.origin.transform_points(np.array([1.5, 1.0]))
        np.testing.assert_allclose(centre, [1.5, -2.0], atol=1e-12)
        assert w.origin.yaw == yaw


def test_the_running_resident_byte_count_follows_every_change() -> None:
    """Admission reads ``resident_bytes`` per ISM, so it is a running count: it must equal the
    sum over the resident tiles after creating, growing, evicting, loading, replacing and
    discarding tiles."""
    stored: dict[tuple[int, int], tuple[list[str], np.ndarray, float]] = {}
    m = new_map(loader=lambda i, j: stored.get((i, j)))

    def truth() -> int:
        return sum(t.nbytes for t in m.resident())

    rng = np.random.default_rng(4)
    inc = random_increments(rng, (20, 20))
    m.fuse("a", inc, GridGeometry(RES, 20, 20, Pose2D(0.05, 0.05, 0.3)))
    assert m.resident_bytes() == truth() > 0
    m.fuse("b", inc, GridGeometry(RES, 20, 20, Pose2D(0.0, 0.0, 0.0)))  # every tile grows
    assert m.resident_bytes() == truth()
    index = next(iter(m.tiles))
    m.evict(index, before=lambda s: stored.__setitem__(s.index, (s.layers, s.data, s.stamp)))
    assert m.resident_bytes() == truth()
    assert m.get_tile(index) is not None  # loaded back
    assert m.resident_bytes() == truth()
    m.insert_tile(index, ["a"], np.zeros((1, T, T), np.int16), 0.0, saved=True)
    assert m.resident_bytes() == truth()
    m.discard(index)
    assert m.resident_bytes() == truth()


# -- ISMs that carry no information leave the map as it is -----------------------------------
def _filled_map() -> TiledMap:
    """A map with content (a real ISM in two layers) to watch for any change."""
    tiled = TiledMap("m", "map", TileLattice(0.05, 64))
    rng = np.random.default_rng(3)
    p = rng.random((90, 110)).astype(np.float32)
    geom = GridGeometry(0.05, 110, 90, Pose2D(-1.0, -0.7, 0.3))
    for layer in ("a", "b"):
        tiled.fuse(layer, logodds.increments(p, "prob_f32"), geom, "biodds")
    return tiled


def _snapshot(tiled: TiledMap) -> dict[tuple[int, int], bytes]:
    return {k: tiled.tile_layers(t)[1].tobytes() for k, t in tiled.tiles.items()}


UNKNOWN_ISMS = {
    "prob_u8_v2 255": (np.full((40, 50), 255, np.uint8), "prob_u8_v2"),
    "prob_u8_v2 127": (np.full((40, 50), 127, np.uint8), "prob_u8_v2"),
    "prob_u8_v2 mixed": (np.where(np.indices((40, 50)).sum(axis=0) % 2 == 0, 127, 255)
                         .astype(np.uint8), "prob_u8_v2"),
    "prob_f32 NaN": (np.full((40, 50), np.nan, np.float32), "prob_f32"),
    "occupancy_i8 -1": (np.full((40, 50), -1, np.int8), "occupancy_i8"),
}


@pytest.mark.parametrize("name", list(UNKNOWN_ISMS))
def test_all_unknown_isms_leave_the_map_bit_identical_after_10000_fusions(name: str) -> None:
    data, encoding = UNKNOWN_ISMS[name]
    tiled = _filled_map()
    before = _snapshot(tiled)
    inc = logodds.increments(data, encoding)
    assert not inc.any()
    aligned = GridGeometry(0.05, 50, 40, Pose2D(-0.5, -0.5, 0.0))
    rotated = GridGeometry(0.07, 50, 40, Pose2D(0.3, -0.2, 0.8))  # warped with biodds
    far = GridGeometry(0.05, 50, 40, Pose2D(40.0, 40.0, 0.0))  # no tile there yet
    for i in range(10_000):
        tiled.fuse("a", inc, (aligned, rotated)[i % 2], "biodds")
    for interp in ("bilinear", "nearest"):
        tiled.fuse("b", inc, rotated, interp)
    tiled.fuse("a", inc, far, "biodds")
    assert _snapshot(tiled) == before  # same tiles, same bytes


def test_prob_u8_128_as_unknown_drives_the_map_to_the_clamp() -> None:
    """Why prob_u8_v2 exists: a prob_u8 ISM that uses 128 for unknown is +8 units a time."""
    tiled = TiledMap("m", "map", TileLattice(0.05, 64))
    geom = GridGeometry(0.05, 8, 8, Pose2D(0.0, 0.0, 0.0))
    inc = logodds.increments(np.full((8, 8), 128, np.uint8), "prob_u8")
    for _ in range(10_000):
        tiled.fuse("a", inc, geom, "biodds")
    assert (tiled.tiles[(0, 0)].planes[0][:8, :8] == HI).all()
