"""Where the ROS 2 maps are published: the region to cover and its stable extent (pure, no zenoh).

nav2's static layer and RViz take a map whose size or origin changed as a new map: the bridge
must send it whole (every topic: each layer and the fused map), while a map of the same extent
is kept current by small ``OccupancyGridUpdate`` rectangles.  So the extent must be stable and
small: it holds the cells the map knows, no more, and when it must grow it grows with headroom,
so that growths are few (each one is a whole grid on every topic) and their sum is a bounded
multiple of the final grid (geometric growth).

The region to cover (:class:`RegionTracker`, ``[ros2] region``):

* ``recent`` (the default): the known cells of the tiles that changed since the last
  publication, i.e. around the ISMs fused lately, by robots with or without a pose.  The extent
  holds all of them until it would pass ``max_cells``; past that it stays while it holds the
  centre of what changed, and is then placed anew there.
* ``robots``: the box of the robots' positions plus ``radius_m``, within the map's known tiles.
* ``known``: every tile the map knows.

Every region is on the map's own cell lattice (so sampling at map resolution is exact).
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

from sogm_service.core.geometry import GridGeometry, Pose2D
from sogm_service.core.map.tiles import TiledMap

Cells = tuple[int, int, int, int]
"""``u0, v0, u1, v1`` on the map's cell lattice (``u1``, ``v1`` exclusive)."""

MARGIN_TILES = 1
"""How far beyond the known tiles a region around the robots may reach (tiles)."""

GROWTH_STEP_CELLS = 32
"""Extents are rounded out to this many cells (1.6 m at 0.05 m): a tidy origin, and a cell box
of a few cells never makes a growth of its own."""

HEADROOM = 0.5
"""A side that grows goes this share of the extent's span (along its axis) beyond what it must
hold: the next growths of a map that keeps growing come less often (a map explored outwards
grows in about log(final / first) / log(1 + HEADROOM) steps per side).  Beyond the known cells
the extent is unknown (-1) and costs bytes for nothing: half a span on one side keeps that
waste below what the saved whole grids cost."""


def cells_of(g: GridGeometry) -> Cells:
    u0, v0 = round(g.origin.x / g.resolution), round(g.origin.y / g.resolution)
    return u0, v0, u0 + g.width, v0 + g.height


def geometry_of(c: Cells, res: float) -> GridGeometry:
    return GridGeometry(res, c[2] - c[0], c[3] - c[1], Pose2D(c[0] * res, c[1] * res, 0.0))


def area(c: Cells) -> int:
    return (c[2] - c[0]) * (c[3] - c[1])


def union(a: Cells, b: Cells) -> Cells:
    return min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3])


def holds(outer: Cells, inner: Cells) -> bool:
    return outer[0] <= inner[0] and outer[1] <= inner[1] and inner[2] <= outer[2] \
        and inner[3] <= outer[3]


def round_out(c: Cells, step: int) -> Cells:
    return (c[0] // step * step, c[1] // step * step, -(-c[2] // step) * step,
            -(-c[3] // step) * step)


def shrink_about_centre(c: Cells, max_cells: int) -> Cells:
    """``c`` shrunk about its centre, keeping the aspect, to at most ``max_cells`` cells."""
    w, h = c[2] - c[0], c[3] - c[1]
    if w * h <= max_cells:
        return c
    f = math.sqrt(max_cells / (w * h))
    nw, nh = max(1, math.floor(w * f)), max(1, math.floor(h * f))
    u0, v0 = c[0] + (w - nw) // 2, c[1] + (h - nh) // 2
    return u0, v0, u0 + nw, v0 + nh


def known_box(planes: Iterable[np.ndarray]) -> tuple[int, int, int, int] | None:
    """The box ``(r0, c0, r1, c1)`` (rows = v, columns = u; ends exclusive) of the cells where
    any plane is not 0 (0 is unknown in the map's log-odds), or None."""
    seen: np.ndarray | None = None
    for p in planes:
        nz = p != 0
        seen = nz if seen is None else seen | nz
    if seen is None:
        return None
    rows, cols = np.flatnonzero(seen.any(axis=1)), np.flatnonzero(seen.any(axis=0))
    if len(rows) == 0:
        return None
    return int(rows[0]), int(cols[0]), int(rows[-1]) + 1, int(cols[-1]) + 1


class RegionTracker:
    """The cells to publish under ``recent``: the known cells of every tile that changed since
    the previous call (tile versions come from one map-wide clock, so "changed" is "version
    above the highest one seen")."""

    def __init__(self) -> None:
        self._seen = -1

    def changed(self, tiled: TiledMap) -> Cells | None:
        """The box of the known cells of the tiles changed since the last call, or None."""
        t = tiled.lattice.tile_size
        box: Cells | None = None
        top = self._seen
        for tile in tiled.resident():
            version = tile.version
            if version <= self._seen:
                continue
            top = max(top, version)
            with tile.lock:  # the planes are written in place by fusers
                b = known_box(tile.planes.values())
            if b is None:
                continue
            i, j = tile.index
            cells = (i * t + b[1], j * t + b[0], i * t + b[3], j * t + b[2])
            box = cells if box is None else union(box, cells)
        self._seen = top
        return box


def robots_region(tiled: TiledMap, robots: Iterable[tuple[float, float]],
                  radius_m: float) -> Cells | None:
    """The robots' box plus ``radius_m``, within the known tiles plus :data:`MARGIN_TILES`."""
    pts = np.asarray(list(robots), dtype=np.float64).reshape(-1, 2)
    pts = pts[np.isfinite(pts).all(axis=1)]
    b = tiled.bounds()
    if len(pts) == 0 or b is None:
        return None
    lo, hi = pts.min(axis=0) - radius_m, pts.max(axis=0) + radius_m
    # Near where the map has tiles: far beyond them every cell is unknown and costs the
    # subscribers bytes for nothing.
    span = tiled.lattice.span
    lo = np.maximum(lo, np.array(b[:2]) - MARGIN_TILES * span)
    hi = np.minimum(hi, np.array(b[2:]) + MARGIN_TILES * span)
    if (hi <= lo).any():
        return None
    return _metric_to_cells(lo, hi, tiled.lattice.resolution)


def known_region(tiled: TiledMap) -> Cells | None:
    """Every tile the map knows."""
    b = tiled.bounds()
    if b is None:
        return None
    return _metric_to_cells(np.array(b[:2]), np.array(b[2:]), tiled.lattice.resolution)


def _metric_to_cells(lo: np.ndarray, hi: np.ndarray, res: float) -> Cells:
    u0, v0 = math.floor(lo[0] / res), math.floor(lo[1] / res)
    return u0, v0, max(u0 + 1, math.ceil(hi[0] / res)), max(v0 + 1, math.ceil(hi[1] / res))


def publish_region(tiled: TiledMap, robots: Iterable[tuple[float, float]] = (), *,
                   mode: str = "robots", radius_m: float = 20.0,
                   max_cells: int = 2048 * 2048) -> GridGeometry | None:
    """The ``robots`` or ``known`` window, shrunk about its centre to at most ``max_cells``
    cells; None when there is nothing.  (``recent`` needs a :class:`RegionTracker`.)"""
    c = robots_region(tiled, robots, radius_m) if mode == "robots" else known_region(tiled)
    if c is None:
        return None
    return geometry_of(shrink_about_centre(c, max_cells), tiled.lattice.resolution)


def _grow(cur: Cells, need: Cells, headroom: float, step: int) -> Cells:
    """``cur`` grown to hold ``need``: each side that must move goes ``headroom`` of the
    span along its axis beyond ``need``, rounded out to ``step``."""
    u = union(cur, need)
    hu, hv = math.ceil(headroom * (u[2] - u[0])), math.ceil(headroom * (u[3] - u[1]))
    grown = (u[0] - hu if need[0] < cur[0] else u[0], u[1] - hv if need[1] < cur[1] else u[1],
             u[2] + hu if need[2] > cur[2] else u[2], u[3] + hv if need[3] > cur[3] else u[3])
    return round_out(grown, step)


def stable_extent(current: GridGeometry | None, needed: GridGeometry, *, step: int,
                  max_cells: int, headroom: float = 0.0) -> GridGeometry:
    """The extent to publish, given the one published so far and the window needed now.

    It stays ``current`` while that holds ``needed``; otherwise it grows to hold both: each
    side that must move goes ``headroom`` (a share of the span) beyond ``needed``, rounded out
    to ``step`` cells; without headroom the union, rounded out.  When that passes
    ``max_cells``, the bare union is tried, then ``current`` stays while it still holds the
    centre of ``needed``, and only then is the extent placed anew on ``needed`` (rounded out,
    if that stays within ``max_cells``).  Every change of the result is a new grid for the
    subscribers.
    """
    res = needed.resolution
    need = cells_of(needed)
    if current is not None and current.resolution == res:
        cur = cells_of(current)
        if holds(cur, need):
            return current
        for c in (_grow(cur, need, headroom, step), round_out(union(cur, need), step),
                  union(cur, need)):
            if area(c) <= max_cells:
                return geometry_of(c, res)
        cu, cv = (need[0] + need[2]) / 2, (need[1] + need[3]) / 2
        if cur[0] <= cu < cur[2] and cur[1] <= cv < cur[3]:
            return current
    placed = round_out(need, step)
    return geometry_of(placed if area(placed) <= max_cells else need, res)
