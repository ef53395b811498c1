"""core/footprint: the arithmetic prices equal what the work would build, for any header."""

from __future__ import annotations

import math

from hypothesis import given, settings
from hypothesis import strategies as st

from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice, window_geometry
from sogm_service.core.map import footprint as fp
from sogm_service.core.map.tiles import TiledMap
from sogm_service.wire.limits import WORLD_EXTENT_M
from tests.conftest import spy_mosaics

finite = st.floats(allow_nan=False, allow_infinity=False)
anything = st.floats(allow_nan=True, allow_infinity=True)


@settings(max_examples=300, deadline=None)
@given(res=st.floats(0.01, 2.0), w=st.integers(1, 200), h=st.integers(1, 200),
       x=st.floats(-500, 500), y=st.floats(-500, 500), yaw=st.floats(-7, 7),
       tile=st.sampled_from([16, 64, 256]))
def test_tile_count_equals_the_listed_tiles(res: float, w: int, h: int, x: float, y: float,
                                            yaw: float, tile: int) -> None:
    lattice = TileLattice(0.05, tile)
    geometry = GridGeometry(res, w, h, Pose2D(x, y, yaw))
    foot = fp.ism_footprint(res, w, h, x, y, yaw, 0.05, tile)
    listed = lattice.tiles_overlapping(geometry)
    assert foot.bounds == geometry.bounds()  # the same floats, bit for bit
    assert foot.tile_count == len(listed)
    i0, j0, i1, j1 = foot.tiles
    assert (i0, j0) == listed[0] and (i1, j1) == listed[-1]


def test_64km_cell_is_priced_without_listing_tiles() -> None:
    # The ISM: one cell of 64 km.  Listing its tiles took 30 s and 3.6 GB.
    foot = fp.ism_footprint(64_000.0, 1, 1, 0.0, 0.0, 0.0, 0.05, 256)
    assert foot.tile_count == (math.floor(64_000 / 12.8) + 1) ** 2
    assert foot.map_cells == (64_000 * 20 + 1) ** 2


@settings(max_examples=300, deadline=None)
@given(res=anything, w=st.integers(1, 1 << 24), h=st.integers(1, 1 << 24), x=anything,
       y=anything, yaw=anything)
def test_world_check_holds_for_any_numbers(res: float, w: int, h: int, x: float, y: float,
                                           yaw: float) -> None:
    bounds = fp.grid_bounds(res, w, h, x, y, yaw)
    if fp.in_world(bounds, WORLD_EXTENT_M):
        assert all(math.isfinite(v) and abs(v) <= WORLD_EXTENT_M for v in bounds)
        foot = fp.ism_footprint(res, w, h, x, y, yaw, 0.05, 256)
        assert all(abs(v) < 2 ** 31 for v in foot.tiles)


@settings(max_examples=200, deadline=None)
@given(x=st.floats(-100, 100), y=st.floats(-100, 100), yaw=st.floats(-4, 4),
       wm=st.floats(0.01, 20), hm=st.floats(0.01, 20), res=st.floats(0.02, 3))
def test_window_price_is_the_window_and_the_box_sample_reads(
        x: float, y: float, yaw: float, wm: float, hm: float, res: float) -> None:
    window = window_geometry(x, y, yaw, wm, hm, res)
    price = fp.window_price(x, y, yaw, wm, hm, res, 0.05)
    assert price is not None
    assert (price.width, price.height) == (window.width, window.height)
    assert price.bounds == window.bounds()
    xmin, ymin, xmax, ymax = window.bounds()
    read_w = (math.ceil(xmax / 0.05) + 1) - (math.floor(xmin / 0.05) - 1)
    read_h = (math.ceil(ymax / 0.05) + 1) - (math.floor(ymin / 0.05) - 1)
    assert (price.read_width, price.read_height) == (read_w, read_h)


def test_window_price_reads_what_mosaic_allocates() -> None:
    """The read box is the mosaic ``sample`` builds: record its shape through the map."""
    tiled = TiledMap("m", "map", TileLattice(0.05, 64))
    tiled.layer_id("a", create=True)
    seen = spy_mosaics(tiled)
    # (a window 10x coarser than the map is gathered instead: tests/unit/core/map/test_gather.py)
    for args in [(1.3, -2.2, 0.4, 3.0, 2.0, 0.1), (0.0, 0.0, 0.0, 4.0, 4.0, 0.05)]:
        tiled.sample(window_geometry(*args), ["a"])
        price = fp.window_price(*args, 0.05)
        assert price is not None and not price.gathered
        assert seen[-1] == (1, price.read_height, price.read_width)


@settings(max_examples=300, deadline=None)
@given(x=anything, y=anything, yaw=anything, wm=anything, hm=anything, res=anything)
def test_window_price_never_raises(x: float, y: float, yaw: float, wm: float, hm: float,
                                   res: float) -> None:
    price = fp.window_price(x, y, yaw, wm, hm, res, 0.05)
    if price is not None:
        assert price.read_cells >= 1 and price.cells >= 1
