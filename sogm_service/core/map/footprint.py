"""What an ISM or a query window will cost, from its header alone (admission).

Pure arithmetic on a handful of floats: no array, no tile list, nothing proportional to the
footprint is ever built, so a 1-cell ISM claiming 64 km cells is priced in microseconds.  The
numbers mirror the code that does the work, operation for operation:

* :func:`grid_bounds` is :meth:`~sogm_service.core.geometry.GridGeometry.bounds` (the same
  float operations in the same order, so the same bits);
* :func:`tile_range` is :meth:`~sogm_service.core.geometry.TileLattice.tiles_overlapping`
  (``tile_count`` == ``len(lattice.tiles_overlapping(geometry))``);
* :func:`window_price` is :func:`~sogm_service.core.geometry.window_geometry` followed by the
  map-cell box :meth:`~sogm_service.core.map.tiles.TiledMap.sample` reads (one cell of margin).

Every function first checks that its numbers are finite and inside the world extent, so the
integers it derives (tile and cell indices) stay far inside int64.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

Bounds = tuple[float, float, float, float]
"""Axis-aligned ``(xmin, ymin, xmax, ymax)`` in metres."""

_MAX_CELLS_PER_AXIS = float(1 << 40)
"""Beyond this many cells per axis a count is absurd whatever the limits (and ``round`` of it
would still be exact): :func:`window_cells` says None instead."""


@dataclass(frozen=True, slots=True)
class Footprint:
    """Where an ISM lands on the tile lattice: its metric box, tile range and counts."""

    bounds: Bounds
    tiles: tuple[int, int, int, int]
    """``(i0, j0, i1, j1)``, inclusive, as ``tiles_overlapping`` lists them."""
    tile_count: int
    map_cells: int
    """Map cells (at map resolution) in the footprint's box: the most a fuse can write."""


@dataclass(frozen=True, slots=True)
class WindowPrice:
    """What a window query costs: the cells it returns and the map cells it reads."""

    width: int
    height: int
    read_width: int
    read_height: int
    bounds: Bounds
    taps: int = 4
    """Map cells the gather path reads per output cell (:func:`gather_taps`)."""

    @property
    def cells(self) -> int:
        return self.width * self.height

    @property
    def mosaic_cells(self) -> int:
        """Map cells of the box the full path builds (``read_width x read_height``)."""
        return self.read_width * self.read_height

    @property
    def gathered(self) -> bool:
        """Whether ``sample`` gathers this window's cells instead of building its box."""
        return prefer_gather(self.taps * self.cells, self.mosaic_cells)

    @property
    def read_cells(self) -> int:
        """Map cells (per layer) sampling this window reads: the taps of every output cell
        when it is gathered, else the whole box."""
        return self.taps * self.cells if self.gathered else self.mosaic_cells


def finite(*values: float) -> bool:
    """Whether every value is a finite number."""
    return all(map(math.isfinite, values))  # map: every ISM's header passes here


def grid_bounds(resolution: float, width: int, height: int, x: float, y: float,
                yaw: float) -> Bounds:
    """The metric box of a ``width x height`` grid of ``resolution`` cells with its corner
    at ``(x, y)``, rotated by ``yaw`` (may be infinite or NaN for absurd inputs: check with
    :func:`in_world`)."""
    if not finite(resolution, x, y, yaw):
        return (math.nan, math.nan, math.nan, math.nan)  # never in the world
    w, h = width * resolution, height * resolution
    c, s = math.cos(yaw), math.sin(yaw)
    xs = (c * 0.0 - s * 0.0 + x, c * w - s * 0.0 + x, c * w - s * h + x, c * 0.0 - s * h + x)
    ys = (s * 0.0 + c * 0.0 + y, s * w + c * 0.0 + y, s * w + c * h + y, s * 0.0 + c * h + y)
    return (min(xs), min(ys), max(xs), max(ys))


def in_world(bounds: Bounds, extent: float) -> bool:
    """Whether the box is finite and inside ``[-extent, extent]^2`` (NaN is never inside)."""
    xmin, ymin, xmax, ymax = bounds
    return -extent <= xmin <= extent and -extent <= ymin <= extent \
        and -extent <= xmax <= extent and -extent <= ymax <= extent


def point_in_world(x: float, y: float, extent: float) -> bool:
    return -extent <= x <= extent and -extent <= y <= extent


def tile_range(bounds: Bounds, span: float) -> tuple[int, int, int, int]:
    """``(i0, j0, i1, j1)`` of the tiles of edge ``span`` metres the box meets (inclusive).

    Raises ``ValueError`` for a box that is not finite (check :func:`in_world` first)."""
    if not finite(*bounds, span) or span <= 0:
        raise ValueError(f"tile range of a non-finite box {bounds} (span {span})")
    xmin, ymin, xmax, ymax = bounds
    return (math.floor(xmin / span), math.floor(ymin / span), math.floor(xmax / span),
            math.floor(ymax / span))


def ism_footprint(resolution: float, width: int, height: int, x: float, y: float, yaw: float,
                  map_resolution: float, tile_size: int) -> Footprint:
    """The footprint of an ISM header on the map's lattice.  Raises ``ValueError`` when the
    header's box is not finite (check :func:`in_world` on :func:`grid_bounds` first)."""
    return bounds_footprint(grid_bounds(resolution, width, height, x, y, yaw), map_resolution,
                            tile_size)


def bounds_footprint(bounds: Bounds, map_resolution: float, tile_size: int) -> Footprint:
    """The footprint of an ISM's metric box (:func:`grid_bounds`) on the map's lattice, for a
    caller that has the box already (it checked it with :func:`in_world`)."""
    i0, j0, i1, j1 = tile_range(bounds, tile_size * map_resolution)
    xmin, ymin, xmax, ymax = bounds
    cols = math.floor(xmax / map_resolution) - math.floor(xmin / map_resolution) + 1
    rows = math.floor(ymax / map_resolution) - math.floor(ymin / map_resolution) + 1
    return Footprint(bounds, (i0, j0, i1, j1), (i1 - i0 + 1) * (j1 - j0 + 1), cols * rows)


def window_cells(width_m: float, height_m: float, resolution: float) -> tuple[int, int] | None:
    """The cell counts :func:`~sogm_service.core.geometry.window_geometry` gives a window
    (``round``, at least 1), or None when they are not finite or absurd (no ``OverflowError``
    can come out of this)."""
    if not (finite(width_m, height_m, resolution) and resolution > 0):
        return None
    fw, fh = width_m / resolution, height_m / resolution
    if not (finite(fw, fh) and abs(fw) < _MAX_CELLS_PER_AXIS and abs(fh) < _MAX_CELLS_PER_AXIS):
        return None
    return max(1, round(fw)), max(1, round(fh))


def window_price(x: float, y: float, yaw: float, width_m: float, height_m: float,
                 resolution: float, map_resolution: float,
                 interp: str = "biodds") -> WindowPrice | None:
    """The cells a window query returns and the map cells it reads (the box ``sample`` builds
    at map resolution, one cell of margin each side), or None when any number is not finite
    or absurd."""
    cells = window_cells(width_m, height_m, resolution)
    if cells is None or not finite(x, y, yaw, map_resolution) or map_resolution <= 0:
        return None
    width, height = cells
    hw, hh = 0.5 * width * resolution, 0.5 * height * resolution
    c, s = math.cos(yaw), math.sin(yaw)
    cx, cy = c * -hw - s * -hh + x, s * -hw + c * -hh + y
    bounds = grid_bounds(resolution, width, height, cx, cy, yaw)
    if not finite(*bounds):
        return None
    xmin, ymin, xmax, ymax = bounds
    fx, fy = xmin / map_resolution, ymin / map_resolution
    gx, gy = xmax / map_resolution, ymax / map_resolution
    if not (finite(fx, fy, gx, gy)
            and max(abs(fx), abs(fy), abs(gx), abs(gy)) < _MAX_CELLS_PER_AXIS):
        return None
    read_w = (math.ceil(gx) + 1) - (math.floor(fx) - 1)
    read_h = (math.ceil(gy) + 1) - (math.floor(fy) - 1)
    return WindowPrice(width, height, read_w, read_h, bounds, gather_taps(interp))


def tile_in_world(i: int, j: int, span: float, extent: float) -> bool:
    """Whether tile ``(i, j)`` (edge ``span`` m) meets the world square: what ``info`` may
    report (an index beyond it could not even be encoded)."""
    lim = math.floor(extent / span) + 1
    return -lim - 1 <= i <= lim and -lim - 1 <= j <= lim


# -- the gather path of coarse windows (:mod:`sogm_service.core.map.gather`) ---------------------
GATHER_ADVANTAGE = 4
"""``sample`` gathers a window's cells only when that reads at most 1/4 of its box."""


def gather_taps(interp: str) -> int:
    """Map cells one output cell reads: 1 for ``nearest``, the 2 x 2 neighbours otherwise."""
    return 1 if interp == "nearest" else 4


def prefer_gather(gathered_cells: int, mosaic_cells: int) -> bool:
    """Whether gathering ``gathered_cells`` map cells beats building a box of
    ``mosaic_cells`` (the one rule ``sample`` and the price both follow)."""
    return gathered_cells * GATHER_ADVANTAGE <= mosaic_cells
